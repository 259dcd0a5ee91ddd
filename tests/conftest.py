"""Every test starts from the same random state: torch's, numpy's and python's generators are seeded before each
one, so that a test drawing unseeded inputs (``torch.randn``) sees the same values in every run, alone or in the
full suite (a draw once made ``test_sampling``'s 1e-13 adjoint check fail in a full run)."""
import random

import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True)
def _seeded():
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)
    yield
