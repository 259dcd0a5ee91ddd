"""Fixtures of the solver tests."""
import pytest

from solver_problems import make_problem


@pytest.fixture(scope="module")
def problem():
    return make_problem()
