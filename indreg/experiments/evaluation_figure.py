"""The evaluation's figure: the volume, its data-determined part and its prior-filled part on one (signed) scale, and
its per-voxel standard deviation on its own; images in one row, volumes as orthogonal slices (one row each).
Drawn with ``indreg.experiments.figures`` (matplotlib imported when called)."""
from __future__ import annotations

import numpy as np

__all__ = ["evaluation_figure", "SD_CMAP"]

#: The standard deviation's colour map (sequential, dark at 0).
SD_CMAP = "magma"


def _np(x):
    return None if x is None else np.asarray(x.detach().cpu().double().numpy() if hasattr(x, "detach") else x,
                                             dtype=np.float64)


def evaluation_figure(volume, data_part, prior_part, sd=None, box=None, unit=None, title: str = "", tilt=None):
    """The figure (matplotlib ``Figure``); ``box`` the domain's ``(min_pt, max_pt)`` (axes in ``unit`` and scale
    bars), ``tilt`` a tilt series' marks (``indreg.experiments.figures.mark_tilt``). Parts that are None are
    left out."""
    from . import figures

    f, d, p, s = _np(volume), _np(data_part), _np(prior_part), _np(sd)
    shown = [a for a in (f, d, p) if a is not None]
    bound = max(max(float(np.abs(a).max()) for a in shown), 1e-12)
    panels = [("volume", f), ("data-determined part", d), ("prior-filled part", p)]
    panels = [(name, a) for name, a in panels if a is not None]
    label = f"one scale, +-{bound:.3g}"
    if f.ndim == 3:   # short row labels (they head a slice's title); the scale in the figure's title
        rows = [(name.split()[0], a, (-bound, bound), figures.DIVERGING) for name, a in panels]
        if s is not None:
            rows.append(("s.d.", s, (0.0, max(float(s.max()), 1e-12)), SD_CMAP))
        head = f"{title}\n" if title else ""
        return figures.ortho_figure(rows, title=f"{head}volume and its parts on {label}; the standard deviation on "
                                    "its own", box=box, unit=unit, tilt=tilt)
    from matplotlib.figure import Figure

    n = len(panels) + (s is not None)
    fig = Figure(figsize=(3.6 * n, 3.6), layout="constrained")
    axes = fig.subplots(1, n, squeeze=False)[0]
    extent = None if box is None else (box[0][0], box[1][0], box[0][1], box[1][1])
    for ax, (name, a) in zip(axes, panels):
        figures.show_image(ax, a, f"{name}\n({label})", -bound, bound, extent, unit=unit, cmap=figures.DIVERGING)
    if s is not None:
        figures.show_image(axes[-1], s, "standard deviation", 0.0, max(float(s.max()), 1e-12), extent, unit=unit,
                           cmap=SD_CMAP)
    if title:
        fig.suptitle(title)
    return fig
