"""Figures laid out as the paper's (fig. Test_suite_1:single_object): matplotlib ``Figure`` objects (no pyplot,
so no global backend is touched; ``savefig`` renders with Agg).

Convention: images are arrays ``(nx, ny)`` with axis 0 = x and axis 1 = y; they are shown as
``np.rot90(image)`` so that x runs to the right and y upwards (upright), grey colormap. Volumes
``(nx, ny, nz)`` are shown as three central orthogonal slices (:func:`orthoslices`): the xy plane (z = centre),
the xz plane (y = centre) and the yz plane (x = centre), each upright in the same way (second axis upwards).
Every image panel has a colour bar (panels on one grey scale share its values); given the domain's box
(``extent`` of an image, ``box = (min_pt, max_pt)`` of a volume) the axes are in the domain's length units.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["PAPER_TIMES", "PLANES", "time_indices", "show_image", "value_range", "paper_figure",
           "deformed_grid_figure", "parts_figure", "parts_ortho_figure", "orthoslices", "ortho_figure",
           "frames_figure", "save", "save_gif", "upscale"]

PAPER_TIMES = (0.25, 0.5, 0.75, 1.0)
PLANES = ("xy", "xz", "yz")
GIF_SIDE = 256   # the movie's least long side in pixels (frames are repeated, nearest)


def _figure(**kwargs) -> Figure:
    """A matplotlib ``Figure`` (matplotlib imported here, on the first figure: the app starts without it)."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def time_indices(num_steps: int, times=PAPER_TIMES) -> list:
    """Indices i of t_i = i / N nearest to ``times`` (exact when 4 divides N)."""
    return [int(round(t * num_steps)) for t in times]


def show_image(ax, image: np.ndarray, title: str, vmin=None, vmax=None, extent=None, axes=("x", "y"),
               colorbar: bool = True):
    """``image`` (nx, ny) upright: ``np.rot90``, grey colormap; with ``extent`` (x_min, x_max, y_min, y_max) the
    axes are labelled ``axes`` in the domain's units, else no ticks; a colour bar unless ``colorbar`` is False.
    Returns the ``AxesImage``."""
    im = ax.imshow(np.rot90(np.asarray(image)), cmap="gray", vmin=vmin, vmax=vmax, extent=extent,
                   interpolation="nearest")
    ax.set_title(title)
    if extent is None:
        ax.set_xticks([])
        ax.set_yticks([])
    else:
        ax.set_xlabel(axes[0], labelpad=1)
        ax.set_ylabel(axes[1], labelpad=1)
        ax.tick_params(labelsize="small")
    if colorbar:
        ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.03).ax.tick_params(labelsize="small")
    return im


def value_range(image) -> str:
    """``"values a to b"`` of an image: what a panel on a shared grey scale may clip."""
    a = np.asarray(image)
    return f"values {float(a.min()):.3g} to {float(a.max()):.3g}"


def paper_figure(template, trajectory, target, det_points, clean_data0, noisy_data0, fbp=None, tv=None,
                 extent=None, title: str = "", angle_deg: float = 0.0):
    """The 3 x 3 layout of the paper's figures 1-2 and 4.

    Row 1: template, t = 0.25, t = 0.5; row 2: t = 0.75, t = 1.0, target; row 3: data at the first angle
    ``angle_deg`` (noise-free blue, noisy red, against the detector coordinate), FBP, TV. ``trajectory`` is
    ``(N + 1, nx, ny)`` = W(nu, I)(t_i). All images share the grey scale of the target (its colour bar on every
    panel); the FBP and TV titles give their own value range (the shared scale clips what lies outside).
    Measured data: ``target=None`` leaves its panel empty (grey scale of the template), ``clean_data0=None``
    plots the data only.
    """
    trajectory = np.asarray(trajectory)
    n = trajectory.shape[0] - 1
    scale = template if target is None else target
    vmin, vmax = float(np.min(scale)), float(np.max(scale))
    fig = _figure(figsize=(12, 11), layout="constrained")
    axes = fig.subplots(3, 3)
    panels = [(template, "Template")]
    panels += [(trajectory[i], f"$t={i / n:.2f}$") for i in time_indices(n)]
    panels += [(target, "Target")]
    for ax, (img, label) in zip(axes.flat[:6], panels):
        if img is None:
            ax.set_axis_off()
        else:
            show_image(ax, img, label, vmin, vmax, extent)
    ax = axes[2, 0]
    if clean_data0 is not None:
        ax.plot(np.asarray(det_points), np.asarray(clean_data0), color="tab:blue", lw=1.5, label="noise-free")
    ax.plot(np.asarray(det_points), np.asarray(noisy_data0), color="tab:red", lw=0.8,
            label="noisy" if clean_data0 is not None else "data")
    ax.set_title(rf"Data at ${angle_deg:.4g}^{{\circ}}$")
    ax.set_xlabel("detector coordinate")
    ax.legend(loc="upper right", fontsize="small")
    ax.set_box_aspect(1)
    for ax, img, label in ((axes[2, 1], fbp, "FBP"), (axes[2, 2], tv, "TV")):
        if img is None:
            ax.set_axis_off()
            ax.set_title(f"{label} (off)")
        else:
            show_image(ax, img, f"{label} ({value_range(img)})", vmin, vmax, extent)
    if title:
        fig.suptitle(title)
    return fig


def deformed_grid_figure(points, every: int = 0, title: str = r"$\varphi_{1,0}$"):
    """The deformed grid: images of the grid lines x = const and y = const under ``points`` = phi (2, nx, ny)."""
    p = np.asarray(points)
    nx, ny = p.shape[1:]
    every = every or max(1, min(nx, ny) // 32)
    fig = _figure(figsize=(5, 5), layout="constrained")
    ax = fig.subplots()
    for i in range(0, nx, every):
        ax.plot(p[0, i, :], p[1, i, :], color="k", lw=0.5)
    for j in range(0, ny, every):
        ax.plot(p[0, :, j], p[1, :, j], color="k", lw=0.5)
    ax.set_aspect("equal")
    ax.set_title(title)
    return fig


def parts_figure(final, summand, remainder, target=None, extent=None, title: str = ""):
    """A reconstruction split into two parts (a model's outputs of kind ``"parts"``; metamorphosis: the
    deformation's ``summand`` W(nu, I) and the intensities' ``remainder`` f(1) - W(nu, I)): f(1), the summand, the
    remainder (own symmetric grey scale, 0 = mid grey) and the target, in a 2 x 2 grid; f(1), the summand and the
    target share the target's grey scale."""
    scale = final if target is None else target
    vmin, vmax = float(np.min(scale)), float(np.max(scale))
    bound = max(float(np.max(np.abs(remainder))), 1e-12)
    fig = _figure(figsize=(9, 8.6), layout="constrained")
    axes = fig.subplots(2, 2).flat
    show_image(axes[0], final, "$f(1)$", vmin, vmax, extent)
    show_image(axes[1], summand, r"$W(\nu, I)$ (deformation part)", vmin, vmax, extent)
    show_image(axes[2], remainder, r"$f(1) - W(\nu, I)$ (intensity part)", -bound, bound, extent)
    if target is None:
        axes[3].set_axis_off()
    else:
        show_image(axes[3], target, "Target", vmin, vmax, extent)
    if title:
        fig.suptitle(title)
    return fig


def parts_ortho_figure(final, summand, remainder, target=None, title: str = "", box=None):
    """``parts_figure`` of volumes: one row of orthogonal slices (``ortho_figure``) for each of f(1), W(nu, I),
    f(1) - W(nu, I) (own symmetric grey scale, 0 = mid grey) and the target (the target's grey scale)."""
    scale = final if target is None else target
    bound = max(float(np.max(np.abs(remainder))), 1e-12)
    panels = [("f(1)", final), ("W(nu, I)", summand),
              (f"f(1) - W(nu, I) (+-{bound:.3g})", remainder, (-bound, bound)), ("target", target)]
    return ortho_figure(panels, float(np.min(scale)), float(np.max(scale)), title=title, box=box)


def orthoslices(volume) -> tuple:
    """The central slices ``(v[:, :, nz//2], v[:, ny//2, :], v[nx//2, :, :])`` of a volume ``(nx, ny, nz)``:
    the xy, xz and yz planes."""
    v = np.asarray(volume)
    if v.ndim != 3:
        raise ValueError(f"orthoslices takes a volume (nx, ny, nz), got shape {v.shape}")
    nx, ny, nz = v.shape
    return v[:, :, nz // 2], v[:, ny // 2, :], v[nx // 2, :, :]


def _plane_extents(box) -> list:
    """``imshow`` extents of the xy, xz and yz planes of the box ``(min_pt, max_pt)`` (None: no axes)."""
    if box is None:
        return [None] * 3
    lo, hi = box
    return [(lo[a], hi[a], lo[b], hi[b]) for a, b in ((0, 1), (0, 2), (1, 2))]


def ortho_figure(panels, vmin=None, vmax=None, title: str = "", box=None):
    """One row of orthogonal slices (xy, xz, yz) per volume: ``panels`` is a list of ``(label, volume)``
    (``volume`` None: an empty row), all on the grey scale ``[vmin, vmax]`` (default: the first volume's), or
    ``(label, volume, (vmin, vmax))`` for a row on its own grey scale; a row's colour bar is at its end. ``box``:
    the domain's ``(min_pt, max_pt)``, for axes in its units."""
    first = next(np.asarray(p[1]) for p in panels if p[1] is not None)
    vmin = float(first.min()) if vmin is None else vmin
    vmax = float(first.max()) if vmax is None else vmax
    fig = _figure(figsize=(9.6, 2.9 * len(panels)), layout="constrained")
    axes = fig.subplots(len(panels), 3, squeeze=False)
    for row, (label, volume, *scale) in zip(axes, panels):
        if volume is None:
            for ax in row:
                ax.set_axis_off()
            row[0].set_title(f"{label} (off)")
            continue
        low, high = scale[0] if scale else (vmin, vmax)
        for ax, plane, image, extent in zip(row, PLANES, orthoslices(volume), _plane_extents(box)):
            im = show_image(ax, image, f"{label}: {plane}", low, high, extent, axes=tuple(plane), colorbar=False)
        fig.colorbar(im, ax=list(row), fraction=0.03, pad=0.02).ax.tick_params(labelsize="small")
    if title:
        fig.suptitle(title)
    return fig


def save(fig, path, dpi: int = 100) -> None:
    fig.savefig(path, dpi=dpi)


def frames_figure(frames: np.ndarray, truth: np.ndarray | None = None, title: str = "", times=None) -> Figure:
    """The frames ``(K, nx, ny)`` of a time series in a row (and the true frames in a second row), upright, on
    the grey scale of the truth (else of the frames), one colour bar; each frame is labelled by its time ``t_k``
    (``times``; None: ``k = 1..K``)."""
    rows = [frames] if truth is None else [frames, truth]
    ref = rows[-1]
    vmin, vmax = float(np.min(ref)), float(np.max(ref))
    k = len(frames)
    labels = [f"$t={t:.3g}$" for t in times] if times is not None else [f"k={i + 1}" for i in range(k)]
    fig = _figure(figsize=(2.2 * k + 1.2, 2.3 * len(rows) + 0.5), layout="constrained")
    axes = fig.subplots(len(rows), k, squeeze=False)
    for r, (row, images) in enumerate(zip(axes, rows)):
        for i, (ax, image) in enumerate(zip(row, images)):
            im = show_image(ax, image, labels[i] if r == 0 else "", vmin, vmax, colorbar=False)
        row[0].set_ylabel("frames" if r == 0 else "truth")
    fig.colorbar(im, ax=axes.ravel().tolist(), fraction=0.03, pad=0.02)
    if title:
        fig.suptitle(title)
    return fig


def upscale(image: np.ndarray, side: int = GIF_SIDE) -> np.ndarray:
    """``image`` repeated (nearest) by the least integer factor that makes its long side at least ``side``."""
    a = np.asarray(image)
    factor = max(1, math.ceil(side / max(a.shape)))
    return np.repeat(np.repeat(a, factor, axis=0), factor, axis=1)


def save_gif(frames: np.ndarray, path, vmin: float, vmax: float, seconds_per_frame: float = 0.25) -> None:
    """An animated GIF of the frames ``(K, nx, ny)`` (upright, grey levels ``[vmin, vmax]`` -> 0..255, upscaled
    (nearest) to at least :data:`GIF_SIDE` pixels on the long side, looping)."""
    import imageio.v2 as imageio

    scale = 255.0 / max(vmax - vmin, 1e-12)
    images = [upscale(np.clip((np.rot90(f) - vmin) * scale, 0, 255).astype(np.uint8)) for f in np.asarray(frames)]
    imageio.mimsave(path, images, duration=seconds_per_frame, loop=0)
