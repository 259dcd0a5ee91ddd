"""The figures of a run (``figure.png``, ``parts.png``, ``evaluation.png``, ``frames.png``, ``frames.gif``) and
TensorBoard's final images, from its result (:func:`indreg.registration.run.build_result`), built with
:mod:`indreg.experiments.figures`.

Convention: as :mod:`indreg.experiments.figures` (images ``(nx, ny)``, axis 0 = x; volumes ``(nx, ny, nz)``); panels
of images are drawn on the domain's extent in its units (``ImageDomain.min_pt`` / ``max_pt``), named by
``logging.length_unit`` (e.g. nm; unset: ``a.u.``, arbitrary units). Every method's panel carries its score (:func:`scores`: SSIM / PSNR against the
target, else the relative data residual); the data residual ``T f - g`` per angle (:func:`residual_sinogram`: a
tilt series' central detector row) is drawn beside the error ``result - target`` and sent to TensorBoard.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from . import figures

__all__ = ["write_figures", "shown_frames", "domain_extent", "to_numpy", "scores", "residual_sinogram", "tilt_marks"]


def to_numpy(x) -> np.ndarray:
    """A tensor as a float64 numpy array on the CPU."""
    return x.detach().to("cpu", torch.float64).numpy()


def shown_frames(n: int) -> set:
    """The indices of the trajectory's frames (of ``n + 1``) that the figures and TensorBoard show."""
    return {0, n // 2, n, *figures.time_indices(n)}


def write_figures(cfg, exp, r, rec: dict, quality: str, out: Path, writer, it: int, kept=None,
                  result=None, wide=None) -> None:
    """figure.png (the paper's layout and a row of errors for images, orthogonal slices for volumes), parts.png
    when the model splits its reconstruction (two outputs of kind ``"parts"``, ``problem.output_kinds``),
    frames.png and frames.gif when it has an output of kind ``"frames"``, and TensorBoard's final images (the
    residual sinogram included); ``quality``: the figures of merit in the titles, ``result``: metrics.json's dict
    (every method's score in its panel). ``kept``: the trajectory's frames :func:`shown_frames` by index, when
    ``r.trajectory`` is None (a volume's run: its trajectory is written frame by frame). ``wide``: the reconstruction
    on a wide box (``exp.box``; ``r`` then holds its field of view), for the data residual."""
    if kept is None:
        traj = to_numpy(r.trajectory)
        n, frame = traj.shape[0] - 1, traj.__getitem__
    else:
        n, frame = max(kept, default=0), lambda i: _host(kept[i])
    volume = exp.domain.ndim == 3
    unit = _unit(cfg)
    kinds = exp.problem.output_kinds
    part_names = [n for n, kind in kinds.items() if kind == "parts" and n in r.outputs]
    parts = tuple(r.outputs[n] for n in part_names) if len(part_names) == 2 else None   # the summands of f(1)
    frames_name = next((n for n, kind in kinds.items() if kind == "frames" and n in r.outputs), None)
    score = scores(result or {}, exp, rec)
    residual = residual_sinogram(exp, r.deformed if wide is None else wide) if frames_name is None else None
    model = str(exp.options.get("model", "lddmm"))
    if cfg.logging.figure:
        figure = _ortho_figure(exp, frame, n, rec, f"{cfg.name}: {quality}", score, unit, residual) if volume else \
            _paper_figure(exp, traj, rec, f"{cfg.name}: {quality}", score, residual, unit)
        figures.save(figure, out / "figure.png")
        if parts is not None:
            figures.save(_parts_figure(exp, r.deformed, parts, f"{cfg.name}: {quality}", unit, model),
                         out / "parts.png")
        if r.data_part is not None or r.uncertainty is not None:   # indreg.evaluation: split and uncertainty
            from .evaluation_figure import evaluation_figure

            figures.save(evaluation_figure(r.deformed, r.data_part, r.prior_part, r.uncertainty,
                                           (exp.domain.min_pt, exp.domain.max_pt), unit,
                                           f"{cfg.name}: what the data determine, what the prior fills",
                                           tilt_marks(exp) if volume else None), out / "evaluation.png")
    if writer.enabled:
        writer.strip("images/trajectory", [frame(0)] + [frame(i) for i in figures.time_indices(n)], it)
        if residual is not None:
            writer.figure("images/residual", _residual_figure(residual, unit), it)
    writer.image("images/deformed_template", r.deformed, it)
    phi = r.deformation   # a volume's: the xy plane through the centre, (x, y) of phi on the central z slice
    if phi is not None:   # None: not kept within max_memory (indreg.registration.budget)
        grid = to_numpy(phi[:2, :, :, phi.shape[-1] // 2] if volume else phi)
        writer.figure("images/deformed_grid", figures.deformed_grid_figure(grid), it)
    if frames_name is not None:   # several time points: the frames in a row, one image each, and a movie
        frames = to_numpy(r.outputs[frames_name])
        truth = exp.targets.get(frames_name)
        times = exp.problem.frame_times()
        writer.strip("images/frames", list(frames), it)
        for k, f in enumerate(frames):
            writer.image(f"images/frames/{k:02d}", f, it)
        if cfg.logging.figure:
            shown = exp.target_64 if exp.target_64 is not None else frames[-1]
            figures.save(figures.frames_figure(frames, None if truth is None else to_numpy(truth),
                                               title=f"{cfg.name}: {quality}", times=times,
                                               extent=domain_extent(exp.domain), unit=unit),
                         out / "frames.png")
            labels = [f"t = {t:.3g}" for t in times] if times is not None else \
                [f"frame {k + 1}" for k in range(len(frames))]
            figures.save_gif(frames, out / "frames.gif", float(shown.min()), float(shown.max()), labels=labels)
    if parts is not None:
        writer.image(f"images/{part_names[0]}", parts[0], it)
        bound = max(float(parts[1].abs().max()), 1e-12)
        writer.image_scaled(f"images/{part_names[1]}", parts[1], it, -bound, bound)
        writer.figure("images/parts", _parts_figure(exp, r.deformed, parts, unit=unit, model=model), it)


#: The figures' length unit when ``logging.length_unit`` is unset: arbitrary units (the paper's box [-16, 16] has
#: none), so that every axis and scale bar says what it measures.
ARBITRARY_UNIT = "a.u."


def _unit(cfg):
    """``logging.length_unit`` (e.g. ``"nm"``), :data:`ARBITRARY_UNIT` when unset."""
    return getattr(cfg.logging, "length_unit", None) or ARBITRARY_UNIT


def scores(result: dict, exp, rec: dict) -> dict:
    """Every method's score for the panel titles: ``{"result" | "template" | <baseline>: {"ssim", "psnr"}}`` from
    metrics.json's ``result`` where a target was given; else ``{"residual": ||T x - g|| / ||g||}`` (the result's
    from ``result``, the baselines' computed here on the data of the fit; images only) and the held-out residual
    where the run had held-out angles."""
    out = {}
    for name, prefix in [("result", ""), ("template", "template_")] + [(k, f"{k}_") for k in rec]:
        if f"{prefix}ssim" in result:
            out[name] = {"ssim": result[f"{prefix}ssim"], "psnr": result[f"{prefix}psnr"]}
    if "result" in out or "residual" not in result:
        if "residual" in result:
            out.setdefault("result", {})["residual"] = result["residual"]
        return out
    out["result"] = {"residual": result["residual"]}
    if "holdout_residual" in result:
        out["result"]["holdout_residual"] = result["holdout_residual"]
    if exp.domain.ndim == 2:
        for k, image in rec.items():
            rel = _relative_residual(exp, image)
            if rel is not None:
                out[k] = {"residual": rel}
    return out


def _relative_residual(exp, image):
    """``||T x - g|| / ||g||`` in the data norm of the fitted data (None where the operator does not apply)."""
    if getattr(exp, "box", None) is not None:   # a baseline's field of view: the wide box's rays need all of it
        return None
    try:
        T, g = exp.ray_transform, exp.noisy_data_64
        with torch.no_grad():
            d = T(image.detach().to(g.dtype)) - g
            return math.sqrt(float(T.inner_data(d, d)) / float(T.inner_data(g, g)))
    except (RuntimeError, TypeError, ValueError, AttributeError):
        return None


def residual_sinogram(exp, deformed):
    """The data residual ``T f - g`` per angle as an array ``(num_angles, det_count)`` (float64): of the whole
    sinogram for images; for a tilt series about y its central detector row (the central y-slice projected
    alone, so a volume of any size costs one slice); None where neither applies (e.g. several frames, a
    distributed run's partial data)."""
    from ..domain import ImageDomain
    from ..forward.ray_transform import RayTransform

    g = exp.noisy_data_64
    T = getattr(exp, "wide_transform", exp.ray_transform)   # a wide box's reconstruction: its operator
    d = T.domain
    try:
        with torch.no_grad():
            if d.ndim == 2:
                res = T(deformed.detach().to("cpu", g.dtype)) - g
                return to_numpy(res.reshape(-1, res.shape[-1])) if res.shape == g.shape else None
            geometry = exp.geometry
            if getattr(geometry, "tilt_axis", None) != "y" or g.dim() != 3:
                return None
            j = d.shape[1] // 2
            lo, hi = d.min_pt, d.max_pt
            plane = ImageDomain((d.shape[0], d.shape[2]), (lo[0], lo[2]), (hi[0], hi[2]))
            T = RayTransform(plane, geometry.slice_geometry)
            res = T(deformed.detach()[:, j, :].to("cpu", torch.float64)) - g[:, j, :].to(torch.float64)
            return to_numpy(res)
    except (RuntimeError, TypeError, ValueError, AttributeError, IndexError):
        return None


def _angles_deg(exp):
    angles = getattr(exp.geometry, "angles", None)
    return None if angles is None else np.degrees(angles.detach().cpu().double().numpy())


def _det_range(exp, count: int) -> tuple:
    det = getattr(exp.geometry, "det_points", None)
    if det is None:
        return -0.5, count - 0.5
    d = det.detach().cpu().double().numpy()
    half = (d[1] - d[0]) / 2 if d.size > 1 else 0.5
    return float(d[0] - half), float(d[-1] + half)


def _residual_figure(residual, unit):
    """TensorBoard's ``images/residual``: the residual sinogram alone."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 4), layout="constrained")
    figures.residual_panel(fig.subplots(), residual, np.arange(residual.shape[0]),
                           (-0.5, residual.shape[1] - 0.5), unit)
    fig.axes[0].set_ylabel("angle index")
    fig.axes[0].set_xlabel("detector bin")
    return fig


def tilt_marks(exp):
    """``figures.mark_tilt``'s ``{"axis", "range_deg"}`` of a tilt series, None for other geometries."""
    axis, angles = getattr(exp.geometry, "tilt_axis", None), _angles_deg(exp)
    if axis is None or angles is None:
        return None
    return {"axis": axis, "range_deg": (float(angles.min()), float(angles.max()))}


def _paper_figure(exp, traj, rec: dict, title: str, score: dict, residual, unit):
    """``figures.paper_figure`` of a 2D run: the data panel shows the first row of the data against the
    detector coordinate where the geometry gives one (``det_points``), else against the bin index."""
    noisy = exp.noisy_data_64.reshape(-1, exp.noisy_data_64.shape[-1])
    clean = None if exp.clean_data_64 is None else exp.clean_data_64.reshape(noisy.shape)[0].numpy()
    det = getattr(exp.geometry, "det_points", None)
    angles = _angles_deg(exp)
    target = None if exp.target_64 is None else exp.target_64.numpy()
    return figures.paper_figure(exp.template_64.numpy(), traj, target,
                                np.arange(noisy.shape[-1]) if det is None else det.numpy(), clean, noisy[0].numpy(),
                                to_numpy(rec["fbp"]) if "fbp" in rec else None,
                                to_numpy(rec["tv"]) if "tv" in rec else None, extent=domain_extent(exp.domain),
                                sirt=to_numpy(rec["sirt"]) if "sirt" in rec else None,
                                title=title, angle_deg=0.0 if angles is None else float(angles[0]),
                                scores=score, residual=residual,
                                angles_deg=None if angles is None or residual is None
                                or len(angles) != residual.shape[0] else angles, unit=unit)


def _ortho_figure(exp, frame, n: int, rec: dict, title: str, score: dict, unit, residual=None):
    """A volume's run: orthogonal slices of the template, W(nu, I) at t = 0.5 and 1 (``frame(i)``, of ``n + 1``),
    target, the error ``result - target`` (signed) and the baselines, each baseline on its own grey scale (its
    value range in its label); every method's score in its label; the tilt axis and the missing wedge marked; the
    residual sinogram of the central detector row (``residual``, :func:`residual_sinogram`) in a last row."""
    def label(name, key, extra=""):
        return "\n".join(t for t in (name, figures.score_text(score.get(key)), extra) if t)

    result = frame(n)
    panels = [(label("template", "template"), exp.template_64.numpy()), ("t = 0.5", frame(n // 2)),
              (label("t = 1 (result)", "result"), result)]
    target = None if exp.target_64 is None else exp.target_64.numpy()
    panels += [("target", target)]
    if target is not None:
        err = np.asarray(result, dtype=np.float64) - target
        bound = max(float(np.abs(err).max()), 1e-12)
        panels += [(f"result - target (+-{bound:.3g})", err, (-bound, bound), figures.DIVERGING)]
    for k, v in rec.items():
        a = _host(v)
        panels += [(label(k.upper(), k, figures.value_range(a)), a, (float(a.min()), float(a.max())))]
    shown = exp.target_64 if exp.target_64 is not None else exp.template_64
    sinogram = None
    if residual is not None:
        angles = _angles_deg(exp)
        sinogram = ("residual $Tf - g$ per tilt, central detector row", residual,
                    angles if angles is not None and len(angles) == residual.shape[0] else np.arange(len(residual)),
                    _det_range(exp, residual.shape[1]))
    return figures.ortho_figure(panels, float(shown.min()), float(shown.max()), title=title,
                                box=(exp.domain.min_pt, exp.domain.max_pt), unit=unit, tilt=tilt_marks(exp),
                                residual=sinogram)


def _parts_figure(exp, final, parts, title: str = "", unit=None, model: str = "metamorphosis"):
    """``figures.parts_figure`` of a run (volumes: ``parts_ortho_figure``): f(1), W(nu, I), f(1) - W(nu, I),
    target; ``model`` in the title."""
    target = None if exp.target_64 is None else exp.target_64.numpy()
    if exp.domain.ndim == 3:
        return figures.parts_ortho_figure(to_numpy(final), to_numpy(parts[0]), to_numpy(parts[1]), target, title=title,
                                          box=(exp.domain.min_pt, exp.domain.max_pt), unit=unit, model=model)
    return figures.parts_figure(to_numpy(final), to_numpy(parts[0]), to_numpy(parts[1]), target,
                                extent=domain_extent(exp.domain), title=title, unit=unit, model=model)


def _host(x) -> np.ndarray:
    """A tensor as a numpy array on the CPU in its own dtype (a volume's panels: no float64 copy)."""
    return x.detach().cpu().numpy()


def domain_extent(domain) -> tuple:
    """``imshow`` extent (x_min, x_max, y_min, y_max) of the domain."""
    (x0, y0), (x1, y1) = domain.min_pt, domain.max_pt
    return x0, x1, y0, y1
