"""The figures of a run (``figure.png``, ``parts.png``, ``frames.png``, ``frames.gif``) and TensorBoard's final
images, from its result (:func:`indreg.run.build_result`), built with :mod:`indreg.experiments.figures`.

Convention: as :mod:`indreg.experiments.figures` (images ``(nx, ny)``, axis 0 = x; volumes ``(nx, ny, nz)``); panels
of images are drawn on the domain's extent in its units (``ImageDomain.min_pt`` / ``max_pt``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from . import figures

__all__ = ["write_figures", "shown_frames", "domain_extent", "to_numpy"]


def to_numpy(x) -> np.ndarray:
    """A tensor as a float64 numpy array on the CPU."""
    return x.detach().to("cpu", torch.float64).numpy()


def shown_frames(n: int) -> set:
    """The indices of the trajectory's frames (of ``n + 1``) that the figures and TensorBoard show."""
    return {0, n // 2, n, *figures.time_indices(n)}


def write_figures(cfg, exp, r, rec: dict, quality: str, out: Path, writer, it: int, kept=None) -> None:
    """figure.png (the paper's layout for images, orthogonal slices for volumes), parts.png when the model
    splits its reconstruction (two outputs of kind ``"parts"``, ``problem.output_kinds``), frames.png and
    frames.gif when it has an output of kind ``"frames"``, and TensorBoard's final images; ``quality``: the
    figures of merit in the titles. ``kept``: the trajectory's frames :func:`shown_frames` by index, when
    ``r.trajectory`` is None (a volume's run: its trajectory is written frame by frame)."""
    if kept is None:
        traj = to_numpy(r.trajectory)
        n, frame = traj.shape[0] - 1, traj.__getitem__
    else:
        n, frame = max(kept, default=0), lambda i: _host(kept[i])
    volume = exp.domain.ndim == 3
    kinds = exp.problem.output_kinds
    part_names = [n for n, kind in kinds.items() if kind == "parts" and n in r.outputs]
    parts = tuple(r.outputs[n] for n in part_names) if len(part_names) == 2 else None   # the summands of f(1)
    frames_name = next((n for n, kind in kinds.items() if kind == "frames" and n in r.outputs), None)
    if cfg.logging.figure:
        figure = _ortho_figure(exp, frame, n, rec, f"{cfg.name}: {quality}") if volume else \
            _paper_figure(exp, traj, rec, title=f"{cfg.name}: {quality}")
        figures.save(figure, out / "figure.png")
        if parts is not None:
            figures.save(_parts_figure(exp, r.deformed, parts, title=f"{cfg.name}: {quality}"), out / "parts.png")
    if writer.enabled:
        writer.strip("images/trajectory", [frame(0)] + [frame(i) for i in figures.time_indices(n)], it)
    writer.image("images/deformed_template", r.deformed, it)
    phi = r.deformation   # a volume's: the xy plane through the centre, (x, y) of phi on the central z slice
    grid = to_numpy(phi[:2, :, :, phi.shape[-1] // 2] if volume else phi)
    writer.figure("images/deformed_grid", figures.deformed_grid_figure(grid), it)
    if frames_name is not None:   # several time points: the frames in a row, one image each, and a movie
        frames = to_numpy(r.outputs[frames_name])
        truth = exp.targets.get(frames_name)
        writer.strip("images/frames", list(frames), it)
        for k, f in enumerate(frames):
            writer.image(f"images/frames/{k:02d}", f, it)
        if cfg.logging.figure:
            shown = exp.target_64 if exp.target_64 is not None else frames[-1]
            figures.save(figures.frames_figure(frames, None if truth is None else to_numpy(truth),
                                               title=f"{cfg.name}: {quality}", times=exp.problem.frame_times()),
                         out / "frames.png")
            figures.save_gif(frames, out / "frames.gif", float(shown.min()), float(shown.max()))
    if parts is not None:
        writer.image(f"images/{part_names[0]}", parts[0], it)
        bound = max(float(parts[1].abs().max()), 1e-12)
        writer.image_scaled(f"images/{part_names[1]}", parts[1], it, -bound, bound)
        writer.figure("images/parts", _parts_figure(exp, r.deformed, parts), it)


def _paper_figure(exp, traj, rec: dict, title: str):
    """``figures.paper_figure`` of a 2D run: the data panel shows the first row of the data against the
    detector coordinate where the geometry gives one (``det_points``), else against the bin index."""
    noisy = exp.noisy_data_64.reshape(-1, exp.noisy_data_64.shape[-1])
    clean = None if exp.clean_data_64 is None else exp.clean_data_64.reshape(noisy.shape)[0].numpy()
    det = getattr(exp.geometry, "det_points", None)
    angles = getattr(exp.geometry, "angles", None)
    target = None if exp.target_64 is None else exp.target_64.numpy()
    return figures.paper_figure(exp.template_64.numpy(), traj, target,
                                np.arange(noisy.shape[-1]) if det is None else det.numpy(), clean, noisy[0].numpy(),
                                to_numpy(rec["fbp"]) if "fbp" in rec else None,
                                to_numpy(rec["tv"]) if "tv" in rec else None, extent=domain_extent(exp.domain),
                                title=title, angle_deg=0.0 if angles is None else float(angles[0]) * 180 / math.pi)


def _ortho_figure(exp, frame, n: int, rec: dict, title: str = ""):
    """A volume's run: orthogonal slices of the template, W(nu, I) at t = 0.5 and 1 (``frame(i)``, of ``n + 1``),
    target and baselines."""
    panels = [("template", exp.template_64.numpy()), ("t = 0.5", frame(n // 2)), ("t = 1", frame(n))]
    panels += [("target", None if exp.target_64 is None else exp.target_64.numpy())]
    panels += [(k.upper(), _host(v)) for k, v in rec.items()]
    shown = exp.target_64 if exp.target_64 is not None else exp.template_64
    return figures.ortho_figure(panels, float(shown.min()), float(shown.max()), title=title,
                                box=(exp.domain.min_pt, exp.domain.max_pt))


def _parts_figure(exp, final, parts, title: str = ""):
    """``figures.parts_figure`` of a run (volumes: ``parts_ortho_figure``): f(1), W(nu, I), f(1) - W(nu, I),
    target."""
    target = None if exp.target_64 is None else exp.target_64.numpy()
    if exp.domain.ndim == 3:
        return figures.parts_ortho_figure(to_numpy(final), to_numpy(parts[0]), to_numpy(parts[1]), target, title=title,
                                          box=(exp.domain.min_pt, exp.domain.max_pt))
    return figures.parts_figure(to_numpy(final), to_numpy(parts[0]), to_numpy(parts[1]), target,
                                extent=domain_extent(exp.domain), title=title)


def _host(x) -> np.ndarray:
    """A tensor as a numpy array on the CPU in its own dtype (a volume's panels: no float64 copy)."""
    return x.detach().cpu().numpy()


def domain_extent(domain) -> tuple:
    """``imshow`` extent (x_min, x_max, y_min, y_max) of the domain."""
    (x0, y0), (x1, y1) = domain.min_pt, domain.max_pt
    return x0, x1, y0, y1
