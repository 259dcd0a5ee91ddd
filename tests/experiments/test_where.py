"""A run says where its outputs are (its last line), and a model other than LDDMM gets its own run folder."""
from pathlib import Path

from indreg.experiments.config import run_dir_name
from indreg.experiments.register import where_line


def test_last_line_names_the_folder_and_the_figures_written(tmp_path):
    (tmp_path / "figure.png").write_bytes(b"")
    (tmp_path / "frames.gif").write_bytes(b"")
    assert where_line("completed", tmp_path) == f"outputs in {tmp_path} (figures: figure.png, frames.gif)"
    assert where_line("converged", Path(tmp_path / "none")) == f"outputs in {tmp_path / 'none'}"


def test_a_stopped_run_names_its_checkpoint_and_how_to_resume(tmp_path):
    line = where_line("interrupted", tmp_path)
    assert line == (f"checkpoint in {tmp_path / 'checkpoint.pt'}: continue with hydra.run.dir={tmp_path} "
                    "resume=true")
    assert where_line("failed", tmp_path).startswith(f"record of the failed run in {tmp_path}")


def test_metamorphosis_is_not_filed_in_the_lddmm_runs_folder():
    assert run_dir_name("suite4_missing_object", "lddmm") == "suite4_missing_object"
    assert run_dir_name("suite4_missing_object", "metamorphosis") == "suite4_missing_object-metamorphosis"
    assert run_dir_name("suite4_missing_object_metamorphosis", "metamorphosis") == \
        "suite4_missing_object_metamorphosis"
    assert run_dir_name("suite1_jv-Mine", "my.models:Mine") == "suite1_jv-Mine"
    assert run_dir_name("../x", "lddmm") == "_x"
