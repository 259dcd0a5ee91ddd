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


@pytest.mark.slow
@pytest.mark.parametrize("user, expected", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE"), ("passive", "passive")])
def test_wait_policy_set_before_torch(user, expected):
    assert _policy(user) == expected


def test_torch_imported_first_is_left_alone():
    """Too late to change the policy: indreg does not pretend it did."""
    script = "import torch, os, indreg; print(os.environ.get('OMP_WAIT_POLICY'))"
    assert _policy(None, script) == "None"


@pytest.mark.slow
def test_heap_allocator_policy_in_a_fresh_process():
    """glibc takes the heap-only policy (Linux); INDREG_MALLOC=system leaves the allocator alone; either way numbers
    are unchanged (only where memory comes from)."""
    import os
    import subprocess
    import sys

    code = ("import torch, indreg._malloc as m; ok = m.use_heap_allocator(); x = torch.arange(2.0 ** 24);"
            "print(ok, float((x * x).sum()))")
    runs = {}
    for value in ("", "system"):
        env = dict(os.environ, INDREG_MALLOC=value)
        out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        runs[value] = out.stdout.split()
    assert runs["system"][0] == "False" and runs[""][1] == runs["system"][1]
    if sys.platform.startswith("linux") and os.path.exists("/lib/x86_64-linux-gnu/libc.so.6"):
        assert runs[""][0] == "True"


@pytest.mark.slow
def test_system_allocator_inside_the_block_only():
    """Inside ``system_allocator()`` a freed large array goes back to the system (glibc's policy); after it the
    heap policy keeps freed arrays again (Linux, glibc)."""
    import os
    import subprocess
    import sys

    if not (sys.platform.startswith("linux") and os.path.exists("/lib/x86_64-linux-gnu/libc.so.6")):
        pytest.skip("glibc only")
    code = ("import torch, indreg._malloc as m\n"
            "def rss(): return next(int(l.split()[1]) for l in open('/proc/self/status') if l.startswith('VmRSS'))\n"
            "assert m.use_heap_allocator()\n"
            "r0 = rss()\n"
            "with m.system_allocator():\n"
            "    x = torch.ones(2 ** 26); del x\n"
            "r1 = rss(); x = torch.ones(2 ** 26); del x\n"
            "print((r1 - r0) // 1024, (rss() - r0) // 1024)")
    env = dict(os.environ, INDREG_MALLOC="")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    inside, after = map(int, out.stdout.split())   # MiB kept after freeing a 256 MiB array
    assert inside < 64 and after > 200
