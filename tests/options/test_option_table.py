"""The option table (indreg.options): the alignment's choices declared once (indreg.alignment.modes, no torch) and
used by the table; one check per option, also for another app's keys (check_value)."""
import subprocess
import sys

import pytest

from indreg import options
from indreg.registration import corrections  # noqa: F401  (registers the alignment and intensity corrections)
from indreg.alignment.modes import ALIGN_GAUGES, ALIGN_MODES, INTERPOLATIONS
from indreg.options import OptionError, check_value


def test_the_alignment_choices_come_from_one_place():
    table = {o.name: o for o in options.all_options()}
    for name, values in (("align", ALIGN_MODES), ("align_gauge", ALIGN_GAUGES),
                         ("align_interpolation", INTERPOLATIONS)):
        assert table[name].default == values[0]
        for value in values:
            assert table[name].check(value, name) == value
        with pytest.raises(OptionError, match=f"{name} must be one of"):
            table[name].check("other", name)


def test_the_option_table_and_the_alignment_choices_load_no_torch():
    code = ("import sys, indreg.alignment.modes, indreg.options, indreg.registration.corrections\n"
            "assert 'torch' not in sys.modules, 'torch loaded'\n"
            "assert 'alignment' in indreg.options.CORRECTIONS and 'intensity' in indreg.options.CORRECTIONS\n"
            "assert list(indreg.options.CORRECTIONS)[:2] == ['alignment', 'intensity']\n")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("name,value,label,message", [
    ("sigma", -1.0, "kernel.sigma", "kernel.sigma must be"),
    ("num_steps", 0, "shooting.num_steps", "shooting.num_steps must be an integer >= 1"),
    ("action", "rigid", "shooting.action", "shooting.action must be one of 'geometric', 'mass_preserving'"),
])
def test_check_value_names_the_key_as_given(name, value, label, message):
    with pytest.raises(OptionError, match=message):
        check_value(name, value, label)
    assert check_value("num_steps", 7, "shooting.num_steps") == 7
