"""indreg sets OMP_WAIT_POLICY=PASSIVE before torch loads OpenMP, and never overrides the user's choice."""
import os
import subprocess
import sys

import pytest

SCRIPT = "import os, indreg, torch; print(os.environ.get('OMP_WAIT_POLICY'))"


def _policy(env_value, script=SCRIPT):
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if env_value is not None:
        env["OMP_WAIT_POLICY"] = env_value
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip().splitlines()[-1]


@pytest.mark.parametrize("user, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE"), ("passive", "passive")])
def test_wait_policy_set_before_torch(user, expected):
    assert _policy(user) == expected


def test_torch_imported_first_is_left_alone():
    """Too late to change the policy: indreg does not pretend it did."""
    script = "import torch, os, indreg; print(os.environ.get('OMP_WAIT_POLICY'))"
    assert _policy(None, script) == "None"
