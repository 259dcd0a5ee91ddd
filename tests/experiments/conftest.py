"""Fixtures of the experiment-app tests (helpers: experiment_helpers.py)."""
import pytest


@pytest.fixture(autouse=True)
def _no_hydra_leak():
    """Hydra's GlobalHydra must not leak between tests."""
    from hydra.core.global_hydra import GlobalHydra

    yield
    GlobalHydra.instance().clear()
