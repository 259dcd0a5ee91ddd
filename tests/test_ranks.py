"""Ranks as a capability (indreg.ranks): the problems say whether they split over ranks, the option table says
which options may change on resume, and the learning app finds its configs without the registration app."""
import subprocess
import sys

import pytest

import indreg
from indreg import options, ranks
from indreg.problems.slabs import SlabwiseRegistration


def test_rank_rows_share_every_row_once():
    for n, world in ((10, 3), (2, 4), (7, 1)):
        shares = [ranks.rank_rows(n, r, world) for r in range(world)]
        assert [i for a, b in shares for i in range(a, b)] == list(range(n))
        assert max(b - a for a, b in shares) - min(b - a for a, b in shares) <= 1


def test_one_process_has_no_group():
    assert ranks.default_group() is None and ranks.process_group(None, "cpu") is None
    assert ranks.rank_world(None) == (0, 1)


def test_problems_declare_whether_they_split_over_ranks():
    assert SlabwiseRegistration.splits_over_ranks and not indreg.IndirectRegistration.splits_over_ranks
    assert not indreg.MetamorphosisRegistration.splits_over_ranks


def test_options_that_may_change_on_resume_are_marked_in_the_table():
    from indreg.experiments.runner import _problem_config

    import indreg.registration.models  # noqa: F401  (the models' options)
    marked = {o.config_key for o in options.all_options() if o.resumable}
    assert marked == {"solver.max_iter", "deformation.slab_size", "deformation.max_memory",
                      "deformation.distributed"}
    plain = {"name": "a", "solver": {"max_iter": 3, "gamma": 1.0}, "deformation": {"slab_size": 4, "sigma": 2}}
    assert _problem_config(plain) == {"solver": {"gamma": 1.0}, "deformation": {"sigma": 2}}


@pytest.mark.slow
def test_learning_app_finds_its_configs_without_the_registration_schema():
    code = ("import sys, indreg.learn.train as t; from indreg.learn.conf import CONFIG_DIR; "
            "assert (CONFIG_DIR / 'train_momentum.yaml').is_file(); t.base_config([]); "
            "print('indreg.experiments.config' in sys.modules, 'indreg.problems.slabs' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["False", "False"]
