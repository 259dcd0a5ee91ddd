"""Render every phantom of indreg.phantoms into one PNG grid (upright: axis 0 = x rightward, y upward).

Usage: python scripts/plot_phantoms.py OUT.png [--size N]
"""
from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from indreg import phantoms  # noqa: E402
from indreg.domain import ImageDomain  # noqa: E402

# the paper's grid for each phantom
PAPER_SIZES = {"j": 64, "v": 64, "six_objects_target": 438, "six_objects_template": 438}


def plot_phantoms(out_path: str, size: int | None = None) -> None:
    """Render all phantoms (each on the paper's grid, or ``size x size``) into ``out_path``."""
    names = phantoms.names()
    cols = 4
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.4 * rows))
    for ax, name in zip(axes.flat, names):
        n = size or PAPER_SIZES.get(name, 256)
        img = phantoms.get(name, ImageDomain.paper(n)).numpy()
        ax.imshow(np.rot90(img), cmap="bone", extent=(-16, 16, -16, 16))
        ax.set_title(f"{name} ({n}x{n})", fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes.flat[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out_path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="output PNG path")
    parser.add_argument("--size", type=int, default=None, help="grid size for every phantom (default: paper's)")
    args = parser.parse_args()
    plot_phantoms(args.out, args.size)
