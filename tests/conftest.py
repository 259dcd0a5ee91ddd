"""Fixtures and options of the whole suite.

- Every test starts from the same random state (``random``, numpy's and torch's global generators seeded with 0):
  a test's random inputs do not depend on the tests that ran before it, and a failure repeats.
- The tests marked ``slow`` (end-to-end runs, seconds to minutes each) run only when asked for: ``pytest -m slow``
  (those alone), ``pytest -m ""`` (everything), any other ``-m`` expression, or a test named by its node id
  (``pytest tests/x.py::test_y``). A plain ``pytest`` runs the rest and reports the slow ones as deselected; CI
  (``.ci/run``) runs both.
"""
import random

import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True)
def _seeded():
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)


def _asked_for_slow(config) -> bool:
    """``-m`` given (even empty), or a test named by its node id on the command line."""
    args = [str(a) for a in config.invocation_params.args]
    return (bool(config.option.markexpr) or any(a.startswith("-m") for a in args)
            or any("::" in str(a) for a in config.args))


def pytest_collection_modifyitems(config, items):
    if _asked_for_slow(config):
        return
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if item.get_closest_marker("slow") is None]
