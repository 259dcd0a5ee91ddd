"""TensorBoard logging of a run (``torch.utils.tensorboard.SummaryWriter``), in ``<run dir>/tensorboard``.

Tags::

    scalars  loss/objective, loss/data_fit, loss/regulariser, optim/grad_norm, optim/step_size,
             deformation/min_jacobian (every iteration; a model with more terms or iterate entries adds
             them, e.g. loss/source_regulariser, optim/source_grad_norm, optim/source_step_size); metrics/ssim, metrics/psnr, metrics/ssim_paper,
             metrics/psnr_paper (every k iterations and at the end); validation/residual (with
             validation.holdout: the held-out angles' relative residual, every k iterations); at the end
             metrics/<baseline>_ssim, metrics/<baseline>_psnr (fbp, tv, sirt) and metrics/template_ssim / _psnr
    images   images/deformed_template (every k), images/trajectory (t_i strip), images/template,
             images/target, images/fbp, images/tv, images/deformed_grid (phi_{1,0}), images/residual (the
             data residual T f - g per angle, a sinogram; a tilt series' central row); a model whose
             reconstruction f(1) has parts adds images/deformation_part (W(nu, I)),
             images/intensity_part (f(1) - W(nu, I), its own grey scale) and images/parts at the end
    hparams  gamma, sigma, N, step_size, action, solver, phantom -> hparam/ssim, hparam/psnr, ... (HParams tab)

View: ``tensorboard --logdir outputs`` (or a multirun dir to compare a sweep).
"""
from __future__ import annotations

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from torch.utils.tensorboard.summary import hparams

from .figures import orthoslices

SCALARS = {"objective": "loss/objective", "data_fit": "loss/data_fit", "regulariser": "loss/regulariser",
           "grad_norm": "optim/grad_norm", "step_size": "optim/step_size",
           "min_jacobian": "deformation/min_jacobian", "source_regulariser": "loss/source_regulariser",
           "source_grad_norm": "optim/source_grad_norm", "source_step_size": "optim/source_step_size",
           "grid": "optim/grid"}   # grid: solver=fast's level
METRICS = ("ssim", "psnr", "ssim_paper", "psnr_paper")


def to_display(image, vmin: float, vmax: float) -> np.ndarray:
    """An image (nx, ny) as an upright (np.rot90) grey CHW array in [0, 1] for ``add_image``; a volume
    (nx, ny, nz) as its three central orthogonal slices (xy, xz, yz, ``figures.orthoslices``) side by side."""
    a = image.detach().cpu().double().numpy() if isinstance(image, torch.Tensor) else np.asarray(image, float)
    if a.ndim == 3:
        return _side_by_side([to_display(s, vmin, vmax) for s in orthoslices(a)])
    a = np.clip((np.rot90(a) - vmin) / max(vmax - vmin, 1e-12), 0.0, 1.0)
    return np.ascontiguousarray(a[None])


def _side_by_side(tiles: list) -> np.ndarray:
    """CHW tiles in a row, bottom-aligned on a white background, with a 2-pixel white gap."""
    height = max(t.shape[1] for t in tiles)
    row = []
    for t in tiles:
        pad = np.ones((1, height - t.shape[1], t.shape[2]))
        row += [np.concatenate((pad, t), axis=1), np.ones((1, height, 2))]
    return np.concatenate(row[:-1], axis=2)


class RunWriter:
    """SummaryWriter with the run's tag layout; ``purge_step`` drops stale events of an interrupted run."""

    def __init__(self, log_dir, purge_step: int | None, vmin: float, vmax: float, enabled: bool = True):
        self.enabled = enabled
        self.vmin, self.vmax = vmin, vmax
        self.writer = SummaryWriter(str(log_dir), purge_step=purge_step) if enabled else None

    def scalars(self, info: dict, step: int) -> None:
        if not self.enabled:
            return
        for key, tag in SCALARS.items():
            v = info.get(key)
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                self.writer.add_scalar(tag, float(v), step)

    def metrics(self, values: dict, step: int) -> None:
        if self.enabled:
            for key in METRICS:
                if key in values:
                    self.writer.add_scalar(f"metrics/{key}", values[key], step)

    def baselines(self, values: dict, names, step: int) -> None:
        """The baselines' scores at the end (``metrics/<name>_ssim``, ``metrics/<name>_psnr``, e.g. fbp, tv, sirt),
        beside the registration's, and the template's (``metrics/template_ssim``): what the run must beat."""
        if self.enabled:
            for name in (*names, "template"):
                for key in ("ssim", "psnr"):
                    if f"{name}_{key}" in values:
                        self.writer.add_scalar(f"metrics/{name}_{key}", values[f"{name}_{key}"], step)

    def validation(self, residual: float, step: int) -> None:
        """The held-out angles' relative residual (``validation.holdout``)."""
        if self.enabled:
            self.writer.add_scalar("validation/residual", residual, step)

    def image(self, tag: str, image, step: int) -> None:
        if self.enabled:
            self.writer.add_image(tag, to_display(image, self.vmin, self.vmax), step, dataformats="CHW")

    def image_scaled(self, tag: str, image, step: int, vmin: float, vmax: float) -> None:
        """An image on its own grey scale ``[vmin, vmax]`` (e.g. a signed intensity change)."""
        if self.enabled:
            self.writer.add_image(tag, to_display(image, vmin, vmax), step, dataformats="CHW")

    def strip(self, tag: str, images, step: int) -> None:
        """Images side by side (e.g. W(nu, I)(t_i) at t = 0, 0.25, ..., 1) with a 2-pixel white gap."""
        if not self.enabled:
            return
        tiles = [to_display(im, self.vmin, self.vmax) for im in images]
        self.writer.add_image(tag, _side_by_side(tiles), step, dataformats="CHW")

    def figure(self, tag: str, fig, step: int) -> None:
        if self.enabled:
            self.writer.add_figure(tag, fig, step, close=True)

    def hparams(self, params: dict, metrics: dict) -> None:
        """HParams tab entry of this run (written into the run's own event file)."""
        if not self.enabled:
            return
        metric_dict = {f"hparam/{k}": float(v) for k, v in metrics.items()}
        for summary in hparams(params, metric_dict):
            self.writer.file_writer.add_summary(summary)
        for tag, v in metric_dict.items():
            self.writer.add_scalar(tag, v)

    def close(self) -> None:
        if self.enabled:
            self.writer.flush()
            self.writer.close()
