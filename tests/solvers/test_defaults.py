"""Every default in one home: the solver classes' defaults are the option table's (``indreg.options``)."""
import inspect

import pytest

from indreg import options
from indreg.registration import solver_registry  # noqa: F401  (the registered solvers)
from indreg.solvers import Algorithm1, MetamorphosisDescent, MetamorphosisTorchOptim, MultilevelSolver, \
    TorchOptimSolver

CLASSES = {Algorithm1: "algorithm1", MetamorphosisDescent: "algorithm1", TorchOptimSolver: "torch",
           MetamorphosisTorchOptim: "torch", MultilevelSolver: "fast"}


@pytest.mark.parametrize("cls", CLASSES, ids=lambda c: c.__name__)
def test_class_defaults_agree_with_the_option_table(cls):
    """A keyword named as a table option that applies to the class's solver defaults to the table's value
    (``register()``'s, or the app's, the paper's, where the option has its own)."""
    solver = CLASSES[cls]
    table = {o.name: o for o in options.CORE if o.group == "solver" and (o.solvers is None or solver in o.solvers)}
    checked = 0
    for name, p in inspect.signature(cls.__init__).parameters.items():
        if name in table and p.default is not inspect.Parameter.empty:
            assert p.default in (table[name].default, table[name].schema_default), \
                f"{cls.__name__}({name}={p.default!r}) but the option table says {table[name].default!r}"
            checked += 1
    assert checked >= 2


def test_fast_inner_algorithm1_takes_the_tables_max_halvings():
    assert inspect.signature(MultilevelSolver.__init__).parameters["max_halvings"].default == \
        options.default("max_halvings")
