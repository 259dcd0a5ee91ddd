"""Results in the layout of the user's files (``RegistrationInputs.as_given``): data made in scikit-image's (its
own ``radon``), ASTRA's, TomoPy's and IMOD's conventions, loaded with that convention and registered; the result
and a baseline as given compare with the user's ground truth, as held, best in that layout of the eight flips and
turns of the square."""
import math

import numpy as np
import pytest
import torch

import indreg
from indreg import phantoms
from indreg.io import conventions
from indreg.io.conventions import CONVENTIONS
from indreg.metrics import ssim

N, HALF = 32, 16.0
RADIANS = np.linspace(0.0, math.pi, 24, endpoint=False)


def turns(a: np.ndarray) -> list:
    """The eight flips and turns of a square array, ``a`` itself first."""
    return [np.rot90(b, k) for b in (a, a.T) for k in range(4)]


def user_case(name: str) -> tuple:
    """``(template, sinogram, angles, truth)`` as the tool holds them (angles in radians): the paper's J (no
    mirror symmetry) as truth, shifted by one cell as template; the data by scikit-image's ``radon`` for
    ``skimage``, else indreg's operator on the convention's domain and detector, exported in the tool's layout,
    angles and units (``indreg.io.conventions``; each checked against the tool in tests of the conventions)."""
    c = CONVENTIONS[name]
    domain = conventions.domain_for(c, N, HALF)
    truth = phantoms.get("j", domain).numpy()
    template = np.roll(truth, 1, axis=0)
    if name == "skimage":
        from skimage.transform import radon
        picture = conventions.image_from_indreg(truth, c)
        sinogram = radon(picture, theta=np.degrees(RADIANS), circle=False)
        det_count = sinogram.shape[0]
    else:
        det_count, h = 46, 2 * HALF / N
        det_min, det_max = conventions.detector_for(c, det_count, h)
        angles = torch.from_numpy(conventions.angles_to_indreg(conventions.angles_from_indreg(RADIANS, c), c))
        T = indreg.RayTransform(domain, indreg.ParallelBeamGeometry(angles=angles, det_count=det_count,
                                                                    det_min=det_min, det_max=det_max))
        sinogram = conventions.sinogram_from_indreg(T(torch.from_numpy(truth)).numpy(), c, h)
    angles = RADIANS if name == "skimage" else conventions.angles_from_indreg(RADIANS, c)
    return (conventions.image_from_indreg(template, c), sinogram, angles, conventions.image_from_indreg(truth, c))


@pytest.mark.parametrize("name", ["skimage", "astra", "tomopy", "imod"])
def test_the_result_as_given_is_in_the_users_layout(name):
    template, sinogram, angles, truth = user_case(name)
    d = indreg.load(template, sinogram, angles=angles, angle_unit="rad", half_width=HALF, convention=name)
    r = indreg.register(d.template, d.data, d.operator, num_steps=4, max_iter=10)
    for image in (r.deformed, indreg.forward.fbp(d.operator, d.data)):
        given = d.as_given(image)
        scores = [ssim(torch.from_numpy(t.copy()), torch.from_numpy(truth)) for t in turns(given)]
        assert scores[0] == max(scores) and scores[0] > sorted(scores)[-2] + 0.1, (name, np.round(scores, 3))
    np.testing.assert_array_equal(d.as_given(d.template), template)          # the round trip, exactly
    stack = d.as_given(r.trajectory)
    assert stack.shape == r.trajectory.shape and np.array_equal(stack[-1], d.as_given(r.trajectory[-1]))


def test_as_given_refuses_another_shape():
    template, sinogram, angles, _ = user_case("skimage")
    d = indreg.load(template, sinogram, angles=angles, angle_unit="rad", half_width=HALF, convention="skimage")
    with pytest.raises(ValueError, match=r"the last axes must be the domain's \(32, 32\)"):
        d.as_given(np.zeros((32, 31)))
