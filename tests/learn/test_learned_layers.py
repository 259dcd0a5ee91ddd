"""examples/learned_layers.py, the plain PyTorch training loop of docs/learned_layers.md: it trains, and the doc shows
its code."""
import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "learned_layers.py"


def _example():
    spec = importlib.util.spec_from_file_location("learned_layers", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_loop_trains_the_unrolled_scheme():
    result = _example().main(n=16, steps=20, batch=4, num_samples=16)
    losses = result["losses"]
    assert sum(losses[-5:]) < 0.7 * sum(losses[:5])               # the indirect loss goes down
    assert result["ssim"] > result["template_ssim"] + 0.03        # and the held-out deformation gets closer


def test_the_doc_shows_the_example_code():
    doc = (ROOT / "docs" / "learned_layers.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", doc, flags=re.S)
    source = EXAMPLE.read_text()
    loop = [b for b in blocks if "optimizer.step()" in b]
    assert loop, "docs/learned_layers.md has no training loop"
    for line in loop[0].splitlines():
        assert line in source, f"docs/learned_layers.md: {line!r} is not in examples/learned_layers.py"
