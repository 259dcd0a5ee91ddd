"""A run says what will run (its first line) and where its outputs are (its last line), and a model other than
LDDMM gets its own run folder."""
from pathlib import Path

import pytest

from indreg.experiments import sources
from indreg.experiments.config import DATA_DIR, run_dir_name
from indreg.experiments.register import plan_line, where_line

from experiment_helpers import compose


def test_first_line_names_the_run_model_solver_data_and_run_dir(tmp_path):
    assert plan_line(compose(), tmp_path) == (
        f"suite1_jv: model lddmm, solver algorithm1 (200 iterations), data phantom j -> v (64^2 cells, parallel "
        f"geometry), float32 on device auto; run dir {tmp_path.resolve()}")
    line = plan_line(compose(["experiment=own_data_example", "solver=lbfgs", "solver.max_iter=7", "dtype=float64",
                              "resume=true"]), tmp_path)
    assert line.startswith("own_data_example: model lddmm, solver lbfgs (7 iterations), data files "
                           f"{DATA_DIR / 'own_data_template.png'} and {DATA_DIR / 'own_data_sinogram.npy'} (parallel "
                           "geometry), float64 on device auto; run dir "), line
    assert line.endswith(" (resume=true: from its checkpoint, if any)")
    assert "data phantom shepp_logan_3d -> shepp_logan_3d_swirl (64 x 64 x 16 cells, tilt_series geometry)" \
        in plan_line(compose(["phantom=shepp_logan_3d", "phantom.thickness=16", "geometry=tilt_series"]), tmp_path)


def _raises(cfg):
    raise RuntimeError("no words")


@pytest.mark.parametrize("describe,words", [(None, "data mine,"), (lambda cfg: "of mine", "data mine of mine,"),
                                            (_raises, "data mine,")])
def test_first_line_has_a_plug_in_sources_words_or_its_name(tmp_path, monkeypatch, describe, words):
    monkeypatch.setitem(sources.SOURCES, "mine", sources.Source("mine", load=lambda cfg: None, describe=describe))
    assert words in plan_line(compose(["data.source=mine"]), tmp_path)


def test_last_line_names_the_folder_and_the_figures_written(tmp_path):
    (tmp_path / "figure.png").write_bytes(b"")
    (tmp_path / "frames.gif").write_bytes(b"")
    assert where_line("completed", tmp_path) == f"outputs in {tmp_path} (figures: figure.png, frames.gif)"
    assert where_line("converged", Path(tmp_path / "none")) == f"outputs in {tmp_path / 'none'}"
    assert where_line("completed", tmp_path, "skimage") == (
        f"outputs in {tmp_path} (figures: figure.png, frames.gif); images and data in convention skimage's layout, "
        "as the files given (velocity, momentum and deformation in indreg's: outputs.json)")


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
