"""The numbers that README.md and docs/ quote beside a cheap command, against what that command prints now: a
failure names the page, the quoted number and the measured one, so a change of results cannot leave the docs
behind. The numbers are read from the pages' text (not copied here). What it compares:

- README.md, "Example": the first Python block run as written; its printed ``status ssim min_jacobian residual``
  against the comment on its ``print`` line (``# completed 0.885 0.135 0.245``);
- docs/cli.md, the first command (``indreg-register``, suite 1): its ``SSIM 0.8855`` against the same registration's
  SSIM (the README's block is suite 1 with the preset's options; the app runs the same);
- docs/own_data.md, "The shipped example": ``SSIM ..., TV ..., FBP ...`` of ``indreg-register
  experiment=own_data_example``, and the status line's "stalls at iteration ... of 200 (step ..., SSIM ...)";
- docs/real_data.md, section 9: the table that ``examples/real_data_haadf.py --table`` prints, when
  ``INDREG_HAADF_DIR`` names the HAADF files' folder (two registrations of minutes each; skipped without it).
"""
import contextlib
import io
import json
import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NUMBER = r"(-?\d+(?:\.\d+)?(?:e-?\d+)?)"


def page(name: str) -> str:
    return (ROOT / name).read_text(encoding="utf-8")


def quoted(text: str, pattern: str, name: str) -> tuple:
    """The numbers ``pattern`` captures in ``text`` (the page ``name``), as strings (their digits matter)."""
    m = re.search(pattern, text)
    assert m, f"{name}: no text matching {pattern!r} (was the page reworded? update this test with it)"
    return m.groups()


def same(doc: str, measured: float, where: str) -> None:
    """``measured`` rounded to the digits ``doc`` shows equals ``doc``."""
    digits = len(doc.split(".")[1].split("e")[0]) if "." in doc else 0
    if "e" in doc:
        shown = f"{measured:.{digits}e}".replace("e-0", "e-").replace("e+0", "e")
        assert float(shown) == float(doc), f"{where}: the doc says {doc}, the command prints {shown}"
    else:
        assert f"{measured:.{digits}f}" == doc, f"{where}: the doc says {doc}, the command prints {measured:.{digits}f}"


@pytest.fixture(scope="module")
def readme_example():
    """README's first Python block, run as written: (its printed line, the comment beside its print)."""
    text = page("README.md")
    block = text[text.index("## Example"):].split("```python\n", 1)[1].split("```", 1)[0]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(block, "README.md", "exec"), {})
    comment = re.search(r"print\(result\.status.*#\s*(.*)", block).group(1).strip()
    return printed.getvalue().split(), comment.split()


@pytest.mark.slow
def test_readme_example_prints_what_its_comment_says(readme_example):
    out, doc = readme_example
    assert out[0] == doc[0], f"README.md, Example: the doc says status {doc[0]}, the code prints {out[0]}"
    for name, d, m in zip(("SSIM", "min Jacobian", "residual"), doc[1:], out[1:]):
        same(d, float(m), f"README.md, Example, {name}")


@pytest.mark.slow
def test_cli_first_command_ssim_is_the_registrations(readme_example):
    (ssim,) = quoted(page("docs/cli.md"), r"indreg-register\s+# suite 1.*?SSIM " + NUMBER, "docs/cli.md")
    out, _ = readme_example
    # the README prints SSIM to Python's full precision; cli.md quotes the app's 4 digits
    same(ssim, float(out[1]), "docs/cli.md, indreg-register (suite 1)")


@pytest.mark.slow
def test_own_data_example_numbers(tmp_path):
    from hydra import compose, initialize_config_dir

    from indreg.experiments import register

    text = page("docs/own_data.md")
    ssim, tv, fbp = quoted(text, r"experiment=own_data_example\s+#.*?SSIM " + NUMBER + ", TV " + NUMBER + ", FBP "
                           + NUMBER, "docs/own_data.md")
    stall, step, stall_ssim = quoted(text, r"stalls at iteration (\d+) of 200 \(step below " + NUMBER + ", SSIM "
                                     + NUMBER, "docs/own_data.md")
    with initialize_config_dir(version_base="1.3", config_dir=str(register.CONFIG_DIR), job_name="docs"):
        cfg = compose(register._CONFIG_NAME, overrides=["experiment=own_data_example", "logging.progress=false",
                                                         "logging.figure=false", "logging.tensorboard=false"])
    m = register.run(cfg, tmp_path)
    where = "docs/own_data.md, the shipped example"
    same(ssim, m["ssim"], f"{where}, SSIM")
    same(tv, m["tv_ssim"], f"{where}, TV")
    same(fbp, m["fbp_ssim"], f"{where}, FBP")
    assert (m["status"], str(m["iterations"])) == ("stalled", stall), \
        f"{where}: the doc says it stalls at iteration {stall}, the run: {m['status']} after {m['iterations']}"
    history = json.loads((tmp_path / "history.json").read_text())
    assert history[-1]["step_size"] < float(step), \
        f"{where}: the doc says the step stalls below {step}, the run's last step is {history[-1]['step_size']:.2e}"
    same(stall_ssim, m["ssim"], f"{where}, SSIM when stalled")


HAADF = os.environ.get("INDREG_HAADF_DIR")


@pytest.mark.slow
@pytest.mark.skipif(not HAADF, reason="INDREG_HAADF_DIR not set (the etspy HAADF files; docs/real_data.md)")
def test_real_data_table_is_what_its_command_prints(tmp_path):
    """docs/real_data.md, section 9: the table and its ratio lines against ``examples/real_data_haadf.py --table``
    (both stacks, the defaults; minutes)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("real_data_haadf", ROOT / "examples" / "real_data_haadf.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        example.main(["--data", HAADF, "--out", str(tmp_path), "--table"])
    out = printed.getvalue()
    table, ratios = out[out.index("| volume | raw: test"):].split("\n\n", 1)
    text = page("docs/real_data.md")
    assert table in text, f"docs/real_data.md, section 9: the table differs from the printed one:\n{table}"
    for line in ratios.strip().splitlines():
        assert line in text, f"docs/real_data.md, section 9: the page lacks the printed line {line!r}"
