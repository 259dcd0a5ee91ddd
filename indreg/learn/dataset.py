"""Synthetic indirect registration data: templates, random smooth geodesic deformations, noisy sinograms."""
from __future__ import annotations

import torch

from .._checks import check_int, check_positive
from ..deform.kernel import GaussianKernel
from ..deform.shooting import GeodesicShooting
from ..forward.fbp import fbp
from ..forward.ray_transform import RayTransform
from ..noise import add_white_noise
from ..phantoms import ellipse_phantom, get as get_phantom


def random_template(domain, generator: torch.Generator, max_ellipses: int = 3) -> torch.Tensor:
    """A random shape: 1..``max_ellipses`` overlapping ellipses of value 1 (clipped), float64 ``(nx, ny)``.

    Ellipses (normalised frame ``[-1, 1]^2``, ``phantoms.ellipse_phantom``) have semi-axes in [0.15, 0.4],
    centres within 0.3 of the origin and any rotation, so a deformed copy stays inside the domain.

    Parameters
    ----------
    domain : ImageDomain
        A 2D domain.
    generator : torch.Generator
        The random draws (advanced).
    max_ellipses : int
        The most ellipses (>= 1).

    Returns
    -------
    torch.Tensor
        Float64 ``(nx, ny)`` in [0, 1].
    """
    count = int(torch.randint(1, max_ellipses + 1, (1,), generator=generator))
    u = torch.rand(count, 5, generator=generator, dtype=torch.float64)
    rows = [(1.0, 0.15 + 0.25 * a, 0.15 + 0.25 * b, 0.6 * cx - 0.3, 0.6 * cy - 0.3, 180.0 * r)
            for a, b, cx, cy, r in u.tolist()]
    return ellipse_phantom(domain, rows).clamp(max=1.0)


def random_momentum(kernel: GaussianKernel, generator: torch.Generator, displacement: float,
                    smoothness: float) -> torch.Tensor:
    """A random smooth initial momentum ``(2, nx, ny)`` (float64) whose velocity peaks at ``displacement``.

    White noise smoothed by a Gaussian of width ``smoothness`` (physical units), tapered by a Gaussian
    window of width a quarter of the domain around its centre (the deformation vanishes near the edge),
    then scaled so that ``max |K m0| = displacement * U(0.5, 1)``.

    Parameters
    ----------
    kernel : GaussianKernel
        ``K`` of V on the domain.
    generator : torch.Generator
        The random draws (advanced).
    displacement : float
        The largest velocity, physical units (before the factor ``U(0.5, 1)``).
    smoothness : float
        Width of the smoothing Gaussian (physical units, > 0).

    Returns
    -------
    torch.Tensor
        Float64 ``(2, nx, ny)``.
    """
    domain = kernel.domain
    noise = torch.randn(2, *domain.shape, generator=generator, dtype=torch.float64)
    m = GaussianKernel(domain, smoothness).apply(noise)
    x = domain.points()
    centre = torch.tensor([(a + b) / 2 for a, b in zip(domain.min_pt, domain.max_pt)], dtype=torch.float64)
    radius = min(domain.extent) / 4
    m = m * torch.exp(-((x - centre[:, None, None]) ** 2).sum(0) / (2 * radius ** 2))
    scale = displacement * (0.5 + 0.5 * float(torch.rand(1, generator=generator, dtype=torch.float64)))
    return m * (scale / kernel.apply(m).abs().max())


class SyntheticDeformationDataset(torch.utils.data.Dataset):
    """``num_samples`` seeded samples of the indirect registration problem with a known geodesic deformation.

    Sample ``i`` (its own generator, seeded by ``(seed, i)``): a template (``random_template``, or a named
    phantom from ``templates``), a random smooth momentum ``m0`` (``random_momentum``), the ground truth
    ``target = W(m0, template)`` by ``shooting``, data ``g = T(target) + noise`` at ``snr_db`` (code convention,
    ``indreg.noise``) and the FBP of ``g`` (Hamming, 0.4, as the paper's baseline). Everything is generated
    once, in float64 and in batches, then stored in ``dtype``; the same seed gives the same data set on
    every process (what data-parallel training relies on).

    Parameters
    ----------
    shooting : GeodesicShooting
        The geodesic layer (its domain and kernel).
    ray_transform : RayTransform
        ``T`` on the shooting's domain.
    num_samples : int
        Samples (>= 1).
    snr_db : float
        The data's SNR (dB, code convention).
    displacement : float
        The momenta's largest velocity (:func:`random_momentum`, > 0).
    smoothness : float
        The momenta's smoothing width (> 0).
    templates : list of str, optional
        Phantom names cycled through as templates (``indreg.phantoms``); None: random shapes.
    seed : int
        The data set's seed (>= 0).
    dtype : torch.dtype
        The stored tensors' dtype.
    batch_size : int
        Samples generated per batch.

    Raises
    ------
    ValueError, TypeError
        A count or width out of range, an unknown phantom name.

    Notes
    -----
    items are dicts of tensors ``template``, ``target``, ``fbp`` ``(nx, ny)``, ``data``
    ``(num_angles, det_count)``, ``momentum`` ``(2, nx, ny)`` and ``index`` (the sample number).
    """

    def __init__(self, shooting: GeodesicShooting, ray_transform: RayTransform, num_samples: int,
                 snr_db: float = 10.0, displacement: float = 3.0, smoothness: float = 3.0, templates=None,
                 seed: int = 0, dtype=torch.float32, batch_size: int = 16):
        self.num_samples = check_int(num_samples, "num_samples", 1)
        self.seed = check_int(seed, "seed", 0)
        check_positive(displacement, "displacement")
        check_positive(smoothness, "smoothness")
        domain = shooting.domain
        named = [get_phantom(name, domain) for name in (templates or [])]
        fields = {k: [] for k in ("template", "target", "data", "fbp", "momentum")}
        for start in range(0, self.num_samples, check_int(batch_size, "batch_size", 1)):
            stop = min(start + batch_size, self.num_samples)
            gens = [torch.Generator().manual_seed(self.seed * 1_000_003 + i) for i in range(start, stop)]
            tmpl = torch.stack([named[i % len(named)] if named else random_template(domain, g)
                                for i, g in zip(range(start, stop), gens)])
            m0 = torch.stack([random_momentum(shooting.kernel, g, displacement, smoothness) for g in gens])
            with torch.no_grad():
                target = shooting(m0, tmpl)
                clean = ray_transform(target)
            noisy = torch.stack([add_white_noise(clean[k], snr_db=snr_db, seed=g)[0] for k, g in enumerate(gens)])
            for key, value in (("template", tmpl), ("target", target), ("data", noisy),
                               ("fbp", fbp(ray_transform, noisy)), ("momentum", m0)):
                fields[key].append(value.to(dtype))
        self.tensors = {k: torch.cat(v) for k, v in fields.items()}

    def __len__(self) -> int:
        return self.num_samples

    def __getitem__(self, i: int) -> dict:
        item = {k: v[i] for k, v in self.tensors.items()}
        item["index"] = torch.tensor(i)
        return item
