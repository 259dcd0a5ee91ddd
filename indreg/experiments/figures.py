"""Figures laid out as the paper's (fig. Test_suite_1:single_object): matplotlib ``Figure`` objects (no pyplot,
so no global backend is touched; ``savefig`` renders with Agg).

Convention: images are arrays ``(nx, ny)`` with axis 0 = x and axis 1 = y; they are shown as
``np.rot90(image)`` so that x runs to the right and y upwards (upright), grey colormap. Volumes
``(nx, ny, nz)`` are shown as three central orthogonal slices (:func:`orthoslices`): the xy plane (z = centre),
the xz plane (y = centre) and the yz plane (x = centre), each upright in the same way (second axis upwards).
Every image panel has a colour bar (panels on one grey scale share its values); given the domain's box
(``extent`` of an image, ``box = (min_pt, max_pt)`` of a volume) the axes are in the domain's length units, named
by ``unit`` (e.g. ``"nm"``; None: the box's own units) and with a scale bar. Signed images (an error
``result - target``, a data residual ``T f - g``, metamorphosis' intensity part) use the diverging map
:data:`DIVERGING`, symmetric about 0 (white).

Longer than 450 lines: the paper's figure layouts, one function per panel kind, sharing the scale bars and units.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["PAPER_TIMES", "PLANES", "DIVERGING", "time_indices", "axis_label", "scale_bar_length", "add_scale_bar",
           "show_image", "show_signed", "value_range", "score_text", "residual_panel", "paper_figure",
           "deformed_grid_figure", "parts_figure", "parts_ortho_figure", "orthoslices", "slice_positions",
           "ortho_figure", "mark_tilt", "frames_figure", "save", "save_gif", "gif_frames", "upscale"]

PAPER_TIMES = (0.25, 0.5, 0.75, 1.0)
PLANES = ("xy", "xz", "yz")
GIF_SIDE = 256   # the movie's least long side in pixels (frames are repeated, nearest)
DIVERGING = "RdBu_r"   # signed images: blue < 0 < red, white at 0


def _figure(**kwargs) -> Figure:
    """A matplotlib ``Figure`` (matplotlib imported here, on the first figure: the app starts without it)."""
    from matplotlib.figure import Figure

    return Figure(**kwargs)


def time_indices(num_steps: int, times=PAPER_TIMES) -> list:
    """Indices i of t_i = i / N nearest to ``times`` (exact when 4 divides N)."""
    return [int(round(t * num_steps)) for t in times]


def axis_label(axis: str, unit=None) -> str:
    """``"x (nm)"``, or ``"x"`` without a unit."""
    return f"{axis} ({unit})" if unit else axis


def scale_bar_length(width: float) -> float:
    """The largest 1, 2 or 5 times a power of ten that is at most a quarter of ``width`` (> 0)."""
    top = width / 4
    power = 10.0 ** math.floor(math.log10(top))
    return max(m * power for m in (1, 2, 5) if m * power <= top * (1 + 1e-12))


def add_scale_bar(ax, extent, unit=None) -> float:
    """A scale bar in the lower right of an image drawn on ``extent`` (x_min, x_max, y_min, y_max), labelled in
    ``unit``; returns its length."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    width, height = abs(extent[1] - extent[0]), abs(extent[3] - extent[2])
    length = scale_bar_length(width)
    ax.add_artist(AnchoredSizeBar(ax.transData, length, f"{length:g} {unit}" if unit else f"{length:g}",
                                  "lower right", pad=0.3, color="gold", frameon=False, size_vertical=height / 80,
                                  fontproperties={"size": "small"}))
    return length


def show_image(ax, image: np.ndarray, title: str, vmin=None, vmax=None, extent=None, axes=("x", "y"),
               colorbar: bool = True, unit=None, cmap: str = "gray", scale_bar: bool = True):
    """``image`` (nx, ny) upright: ``np.rot90``, colour map ``cmap`` (grey); with ``extent`` (x_min, x_max, y_min,
    y_max) the axes are labelled ``axes`` in ``unit`` (the domain's units) and a scale bar is drawn, else no
    ticks; a colour bar unless ``colorbar`` is False. Returns the ``AxesImage``."""
    im = ax.imshow(np.rot90(np.asarray(image)), cmap=cmap, vmin=vmin, vmax=vmax, extent=extent,
                   interpolation="nearest")
    ax.set_title(title, fontsize="medium")
    if extent is None:
        ax.set_xticks([])
        ax.set_yticks([])
    else:
        ax.set_xlabel(axis_label(axes[0], unit), labelpad=1)
        ax.set_ylabel(axis_label(axes[1], unit), labelpad=1)
        ax.tick_params(labelsize="small")
        if scale_bar:
            add_scale_bar(ax, extent, unit)
    if colorbar:
        ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.03).ax.tick_params(labelsize="small")
    return im


def show_signed(ax, image: np.ndarray, title: str, extent=None, axes=("x", "y"), unit=None,
                colorbar: bool = True, scale_bar: bool = True):
    """A signed image (an error, an intensity change) on :data:`DIVERGING`, symmetric about 0."""
    bound = max(float(np.max(np.abs(image))), 1e-12)
    return show_image(ax, image, title, -bound, bound, extent, axes, colorbar, unit, DIVERGING, scale_bar)


def value_range(image) -> str:
    """``"values a to b"`` of an image: what a panel on a shared grey scale may clip."""
    a = np.asarray(image)
    return f"values {float(a.min()):.3g} to {float(a.max()):.3g}"


def score_text(scores) -> str:
    """A method's score for a panel title: ``"SSIM 0.886, PSNR 24.19 dB"`` from ``{"ssim", "psnr"}``, else its
    held-out or data residual (``holdout_residual`` / ``residual``, relative); ``""`` for none."""
    if not scores:
        return ""
    if "ssim" in scores:
        return f"SSIM {scores['ssim']:.4f}, PSNR {scores['psnr']:.2f} dB"
    if "holdout_residual" in scores:
        return f"held-out residual {scores['holdout_residual']:.4f}"
    return f"data residual {scores['residual']:.4f}" if "residual" in scores else ""


def _titled(label: str, scores) -> str:
    text = score_text(scores)
    return f"{label}\n{text}" if text else label


def residual_panel(ax, residual: np.ndarray, angles_deg, det_range, unit=None, title: str = ""):
    """The data residual ``T f - g`` per angle: a sinogram ``(num_angles, det_count)`` on :data:`DIVERGING`
    (symmetric about 0), detector coordinate across, angle (deg) upwards; angles need not be uniform (rows are
    drawn in the data's order, labelled by their angles)."""
    r = np.asarray(residual)
    bound = max(float(np.max(np.abs(r))), 1e-12)
    k = r.shape[0]
    im = ax.imshow(r, cmap=DIVERGING, vmin=-bound, vmax=bound, aspect="auto", interpolation="nearest",
                   origin="lower", extent=(det_range[0], det_range[1], -0.5, k - 0.5))
    ticks = np.unique(np.linspace(0, k - 1, min(k, 5)).round().astype(int))
    ax.set_yticks(ticks, [f"{float(angles_deg[i]):.3g}" for i in ticks])
    ax.set_xlabel(axis_label("detector coordinate", unit))
    ax.set_ylabel("angle (deg)")
    ax.tick_params(labelsize="small")
    ax.set_title(title or "residual $Tf - g$ per angle", fontsize="medium")
    ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.03).ax.tick_params(labelsize="small")
    return im


def paper_figure(template, trajectory, target, det_points, clean_data0, noisy_data0, fbp=None, tv=None,
                 extent=None, title: str = "", angle_deg: float = 0.0, scores=None, residual=None, angles_deg=None,
                 unit=None, data_unit: str = "", sirt=None):
    """The 3 x 3 layout of the paper's figures 1-2 and 4, and a fourth row of errors.

    Row 1: template, t = 0.25, t = 0.5; row 2: t = 0.75, t = 1.0 (the result), target; row 3: data at the first
    angle ``angle_deg`` (noise-free blue, noisy red, against the detector coordinate; y axis ``data_unit``, default
    "line integral"), FBP, TV; row 4 (when a target or a ``residual`` is given): the error ``result - target`` and
    that of the best baseline (by SSIM: FBP, ``sirt`` if given, TV) on one diverging scale, and the data residual
    ``T f - g`` per angle (``residual`` ``(num_angles, det_count)``, ``angles_deg``). ``trajectory`` is
    ``(N + 1, nx, ny)`` = W(nu, I)(t_i). All images share the grey scale of the target (its colour bar on every
    panel); the FBP and TV titles give their own value range (the shared scale clips what lies outside).
    ``scores``: ``{"result" | "fbp" | "sirt" | "tv" | "template": {"ssim", "psnr"} or {"residual"}}``, in the
    panels' titles (:func:`score_text`). ``unit``: the domain's length unit (axes, scale bar). Measured data:
    ``target=None`` leaves its panel empty (grey scale of the template), ``clean_data0=None`` plots the data only.
    """
    scores = scores or {}
    trajectory = np.asarray(trajectory)
    n = trajectory.shape[0] - 1
    scale = template if target is None else target
    vmin, vmax = float(np.min(scale)), float(np.max(scale))
    errors = target is not None or residual is not None
    fig = _figure(figsize=(12, 14.8 if errors else 11), layout="constrained")
    axes = fig.subplots(4 if errors else 3, 3)
    panels = [(template, _titled("Template", scores.get("template")))]
    panels += [(trajectory[i], f"$t={i / n:.2f}$") for i in time_indices(n)]
    panels[-1] = (trajectory[n], _titled(f"$t={1:.2f}$ (result)", scores.get("result")))
    panels += [(target, "Target")]
    for ax, (img, label) in zip(axes.flat[:6], panels):
        if img is None:
            ax.set_axis_off()
        else:
            show_image(ax, img, label, vmin, vmax, extent, unit=unit)
    ax = axes[2, 0]
    if clean_data0 is not None:
        ax.plot(np.asarray(det_points), np.asarray(clean_data0), color="tab:blue", lw=1.5, label="noise-free")
    ax.plot(np.asarray(det_points), np.asarray(noisy_data0), color="tab:red", lw=0.8,
            label="noisy" if clean_data0 is not None else "data")
    ax.set_title(rf"Data at ${angle_deg:.4g}^{{\circ}}$", fontsize="medium")
    ax.set_xlabel(axis_label("detector coordinate", unit))
    ax.set_ylabel(data_unit or "line integral")
    ax.legend(loc="upper right", fontsize="small")
    ax.set_box_aspect(1)
    for ax, img, key, label in ((axes[2, 1], fbp, "fbp", "FBP"), (axes[2, 2], tv, "tv", "TV")):
        if img is None:
            ax.set_axis_off()
            ax.set_title(f"{label} (off)")
        else:
            show_image(ax, img, f"{_titled(label, scores.get(key))}\n({value_range(img)})", vmin, vmax, extent,
                       unit=unit)
    if errors:
        _error_row(axes[3], trajectory[n], target, {"FBP": fbp, "SIRT": sirt, "TV": tv}, scores, residual,
                   angles_deg, det_points, extent, unit)
    if title:
        fig.suptitle(title)
    return fig


def _error_row(row, result, target, baselines: dict, scores: dict, residual, angles_deg, det_points, extent, unit):
    """The fourth row of :func:`paper_figure`: result - target, the best baseline's error on the same scale (the
    larger of the two errors), and the residual sinogram ``T f - g``."""
    shown = [b for b in baselines.items() if b[1] is not None]
    if target is not None:
        err = np.asarray(result) - np.asarray(target)
        others = {k: np.asarray(v) - np.asarray(target) for k, v in shown}
        best = max(others, key=lambda k: scores.get(k.lower(), {}).get("ssim", -1.0)) if others else None
        shared = (err,) if best is None else (err, others[best])   # the two panels' scale
        bound = max([float(np.max(np.abs(e))) for e in shared] + [1e-12])
        show_image(row[0], err, "error: result $-$ target", -bound, bound, extent, unit=unit, cmap=DIVERGING)
        if best is not None:
            show_image(row[1], others[best], f"error: {best} $-$ target (same scale)", -bound, bound, extent,
                       unit=unit, cmap=DIVERGING)
        else:
            row[1].set_axis_off()
    else:
        row[0].set_axis_off()
        row[1].set_axis_off()
    if residual is None:
        row[2].set_axis_off()
        return
    det = np.asarray(det_points, dtype=float)
    half = (det[1] - det[0]) / 2 if det.size > 1 else 0.5
    angles = np.arange(np.asarray(residual).shape[0]) if angles_deg is None else angles_deg
    rel = score_text({"residual": scores["result"]["residual"]}) if "residual" in scores.get("result", {}) else ""
    residual_panel(row[2], residual, angles, (det[0] - half, det[-1] + half), unit,
                   "residual $Tf - g$ per angle" + (f"\n({rel})" if rel else ""))


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


def parts_figure(final, summand, remainder, target=None, extent=None, title: str = "", unit=None,
                 model: str = "metamorphosis"):
    """A reconstruction split into two parts (a model's outputs of kind ``"parts"``; metamorphosis: the
    deformation's ``summand`` W(nu, I) and the intensities' ``remainder`` f(1) - W(nu, I)): f(1), the summand, the
    remainder (signed: :data:`DIVERGING`, symmetric about 0) and the target, in a 2 x 2 grid; f(1), the summand and
    the target share the target's grey scale. ``model`` opens the title."""
    scale = final if target is None else target
    vmin, vmax = float(np.min(scale)), float(np.max(scale))
    fig = _figure(figsize=(9, 8.6), layout="constrained")
    axes = fig.subplots(2, 2).flat
    show_image(axes[0], final, "$f(1)$", vmin, vmax, extent, unit=unit)
    show_image(axes[1], summand, r"$W(\nu, I)$ (deformation part)", vmin, vmax, extent, unit=unit)
    show_signed(axes[2], remainder, r"$f(1) - W(\nu, I)$ (intensity part)", extent, unit=unit)
    if target is None:
        axes[3].set_axis_off()
    else:
        show_image(axes[3], target, "Target", vmin, vmax, extent, unit=unit)
    fig.suptitle(f"{model}: {title}" if title else model)
    return fig


def parts_ortho_figure(final, summand, remainder, target=None, title: str = "", box=None, unit=None,
                       model: str = "metamorphosis"):
    """``parts_figure`` of volumes: one row of orthogonal slices (``ortho_figure``) for each of f(1), W(nu, I),
    f(1) - W(nu, I) (signed: :data:`DIVERGING`, symmetric about 0) and the target (the target's grey scale)."""
    scale = final if target is None else target
    bound = max(float(np.max(np.abs(remainder))), 1e-12)
    panels = [("f(1)", final), ("W(nu, I)", summand),
              (f"f(1) - W(nu, I) (+-{bound:.3g})", remainder, (-bound, bound), DIVERGING), ("target", target)]
    return ortho_figure(panels, float(np.min(scale)), float(np.max(scale)),
                        title=f"{model}: {title}" if title else model, box=box, unit=unit)


def orthoslices(volume) -> tuple:
    """The central slices ``(v[:, :, nz//2], v[:, ny//2, :], v[nx//2, :, :])`` of a volume ``(nx, ny, nz)``:
    the xy, xz and yz planes."""
    v = np.asarray(volume)
    if v.ndim != 3:
        raise ValueError(f"orthoslices takes a volume (nx, ny, nz), got shape {v.shape}")
    nx, ny, nz = v.shape
    return v[:, :, nz // 2], v[:, ny // 2, :], v[nx // 2, :, :]


def slice_positions(shape, box) -> tuple:
    """The coordinates ``(z, y, x)`` of the planes :func:`orthoslices` cuts (xy at z, xz at y, yz at x): the
    centres of cells ``n // 2`` of the box ``(min_pt, max_pt)``."""
    lo, hi = box
    return tuple(lo[a] + (shape[a] // 2 + 0.5) * (hi[a] - lo[a]) / shape[a] for a in (2, 1, 0))


def _plane_extents(box) -> list:
    """``imshow`` extents of the xy, xz and yz planes of the box ``(min_pt, max_pt)`` (None: no axes)."""
    if box is None:
        return [None] * 3
    lo, hi = box
    return [(lo[a], hi[a], lo[b], hi[b]) for a, b in ((0, 1), (0, 2), (1, 2))]


def mark_tilt(axes, tilt: dict, box) -> None:
    """A single-axis tilt series about y (beam along z at tilt 0) on the xy, xz, yz panels ``axes``: the tilt axis
    (dashed, in xy and yz) and, in xz (the plane the tilts turn in), the beam directions of the first and last
    tilts (dotted): the directions outside that fan are the missing wedge. ``tilt``: ``{"axis": "y", "range_deg":
    (min, max)}``; other axes are not marked."""
    if tilt is None or tilt.get("axis") != "y" or box is None:
        return
    lo, hi = box
    c = [(a + b) / 2 for a, b in zip(lo, hi)]
    xy, xz, yz = axes
    xy.axvline(c[0], color="cyan", ls="--", lw=0.8)
    xy.text(c[0], hi[1], " tilt axis", color="cyan", fontsize="x-small", va="top")
    yz.axhline(c[2], color="cyan", ls="--", lw=0.8)
    yz.text(lo[1], c[2], "tilt axis", color="cyan", fontsize="x-small", va="bottom")
    r = max(hi[0] - lo[0], hi[2] - lo[2])
    for deg in tilt["range_deg"]:
        t = math.radians(deg)
        dx, dz = -math.sin(t) * r, math.cos(t) * r
        xz.plot([c[0] - dx, c[0] + dx], [c[2] - dz, c[2] + dz], color="cyan", ls=":", lw=1.0)
    xz.set_xlim(lo[0], hi[0])
    xz.set_ylim(lo[2], hi[2])
    a, b = tilt["range_deg"]
    xz.text(lo[0], hi[2], f" beams {a:.3g} to {b:.3g} deg;\n missing wedge outside", color="cyan",
            fontsize="x-small", va="top")


def ortho_figure(panels, vmin=None, vmax=None, title: str = "", box=None, unit=None, tilt=None, residual=None):
    """One row of orthogonal slices (xy, xz, yz) per volume: ``panels`` is a list of ``(label, volume)``
    (``volume`` None: an empty row), all on the grey scale ``[vmin, vmax]`` (default: the first volume's), or
    ``(label, volume, (vmin, vmax))`` for a row on its own scale, ``(label, volume, (vmin, vmax), cmap)`` on its
    own colour map too (signed: :data:`DIVERGING`); a row's colour bar is at its end. ``box``: the domain's
    ``(min_pt, max_pt)``, for axes in ``unit``, a scale bar and each plane's position in its title; ``tilt``: see
    :func:`mark_tilt`. A row's label (it may hold a second line, e.g. the score) heads its first panel.
    ``residual``: ``(title, sinogram, angles_deg, det_range)`` of a last row, the data residual ``T f - g`` of
    one detector row per angle (:func:`residual_panel`)."""
    first = next(np.asarray(p[1]) for p in panels if p[1] is not None)
    vmin = float(first.min()) if vmin is None else vmin
    vmax = float(first.max()) if vmax is None else vmax
    where = [""] * 3
    if box is not None:
        z, y, x = slice_positions(first.shape, box)
        u = f" {unit}" if unit else ""
        where = [f" at z = {z:.3g}{u}", f" at y = {y:.3g}{u}", f" at x = {x:.3g}{u}"]
    rows = len(panels) + (residual is not None)
    fig = _figure(figsize=(10.4, 3.3 * rows), layout="constrained")
    axes = fig.subplots(rows, 3, squeeze=False)
    if residual is not None:
        text, sinogram, angles_deg, det_range = residual
        residual_panel(axes[-1][0], sinogram, angles_deg, det_range, unit, text)
        for ax in axes[-1][1:]:
            ax.set_axis_off()
    for row, (label, volume, *style) in zip(axes, panels):
        if volume is None:
            for ax in row:
                ax.set_axis_off()
            row[0].set_title(f"{label} (off)")
            continue
        low, high = style[0] if style else (vmin, vmax)
        cmap = style[1] if len(style) > 1 else "gray"
        for i, (ax, plane, image, extent, at) in enumerate(zip(row, PLANES, orthoslices(volume), _plane_extents(box),
                                                              where)):
            head = (f"{label}\n" if "\n" in label else f"{label}: ") if i == 0 else ""
            im = show_image(ax, image, f"{head}{plane}{at}", low, high, extent,
                            axes=tuple(plane), colorbar=False, unit=unit, cmap=cmap)
        mark_tilt(row, tilt, box)
        fig.colorbar(im, ax=list(row), fraction=0.03, pad=0.02).ax.tick_params(labelsize="small")
    if title:
        fig.suptitle(title)
    return fig


def save(fig, path, dpi: int = 100) -> None:
    """``fig`` as a PNG at ``path``, written to a fresh file renamed over ``path`` (no link followed)."""
    from .._outfiles import replacing

    with replacing(path) as new:
        fig.savefig(new, dpi=dpi)


def frames_figure(frames: np.ndarray, truth: np.ndarray | None = None, title: str = "", times=None,
                  extent=None, unit=None) -> Figure:
    """The frames ``(K, nx, ny)`` of a time series in a row (and the true frames in a second row), upright, on
    the grey scale of the truth (else of the frames), one colour bar; each frame is labelled by its time ``t_k``
    (``times``; None: ``k = 1..K``); with ``extent`` a scale bar in ``unit`` on the first frame."""
    rows = [frames] if truth is None else [frames, truth]
    ref = rows[-1]
    vmin, vmax = float(np.min(ref)), float(np.max(ref))
    k = len(frames)
    labels = [f"$t={t:.3g}$" for t in times] if times is not None else [f"k={i + 1}" for i in range(k)]
    fig = _figure(figsize=(2.2 * k + 1.2, 2.3 * len(rows) + 0.5), layout="constrained")
    axes = fig.subplots(len(rows), k, squeeze=False)
    for r, (row, images) in enumerate(zip(axes, rows)):
        for i, (ax, image) in enumerate(zip(row, images)):
            im = show_image(ax, image, labels[i] if r == 0 else "", vmin, vmax, extent, colorbar=False, unit=unit,
                            scale_bar=i == 0)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_xlabel("")
            ax.set_ylabel("")
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


def gif_frames(frames: np.ndarray, vmin: float, vmax: float, labels=None) -> list:
    """The movie's frames: upright, grey levels ``[vmin, vmax]`` -> 0..255, upscaled (nearest) to at least
    :data:`GIF_SIDE` pixels on the long side, each with its label (e.g. ``"t = 0.25"``) drawn in its top left
    corner (``uint8`` RGB arrays)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    scale = 255.0 / max(vmax - vmin, 1e-12)
    out = []
    for i, f in enumerate(np.asarray(frames)):
        grey = upscale(np.clip((np.rot90(f) - vmin) * scale, 0, 255).astype(np.uint8))
        if labels is None:
            out.append(grey)
            continue
        h, w = grey.shape
        fig = _figure(figsize=(w / 100, h / 100), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.imshow(grey, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        ax.set_axis_off()
        ax.text(0.03, 0.97, labels[i], transform=ax.transAxes, color="yellow", va="top", fontsize=max(8, h // 20))
        fig.canvas.draw()
        out.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    return out


def save_gif(frames: np.ndarray, path, vmin: float, vmax: float, seconds_per_frame: float = 0.25,
             labels=None) -> None:
    """An animated GIF of the frames ``(K, nx, ny)`` (:func:`gif_frames`: upright, grey levels ``[vmin, vmax]``,
    upscaled, each labelled by ``labels``), looping, each frame shown ``seconds_per_frame`` (imageio's GIF writer
    takes the delay in milliseconds)."""
    import imageio.v2 as imageio

    from .._outfiles import replacing

    with replacing(path) as new:   # a fresh file renamed over path: no link followed
        imageio.mimsave(new, gif_frames(frames, vmin, vmax, labels), duration=1000.0 * seconds_per_frame, loop=0)
