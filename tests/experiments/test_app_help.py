"""``--help`` composed once (indreg.experiments.cli.print_help) prints Hydra's own ``--help`` text, for both apps, with
and without overrides; anything else goes to Hydra."""
import logging
import sys

import hydra
import pytest

from indreg.experiments import cli as app_help, register
from indreg.learn import entry


def _hydra_help(capsys, monkeypatch, config_dir, config_name, overrides) -> str:
    """What Hydra's own ``--help`` prints for the app (its decorated main, run in this process)."""
    monkeypatch.setattr(sys, "argv", ["prog", "--help", *overrides])
    root = logging.getLogger()
    handlers = list(root.handlers)
    try:
        with pytest.raises(SystemExit) as exc:
            hydra.main(version_base="1.3", config_path=str(config_dir), config_name=config_name)(lambda cfg: None)()
    finally:   # Hydra's logging set-up (a handler on capsys' stream) would outlive the test
        root.handlers[:] = handlers
    assert exc.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("app, overrides", [   # Hydra's own help: 1-6 s each (idle to loaded)
    ("register", []), pytest.param("register", ["experiment=suite3_shepp_logan"], marks=pytest.mark.slow),
    pytest.param("train", [], marks=pytest.mark.slow), ("train", ["model=unrolled", "seed=3"])])
def test_help_is_hydras_help(capsys, monkeypatch, app, overrides):
    register._register_schema()   # the schema in Hydra's ConfigStore, for both
    config_dir, name = (register._CONFIG, "config") if app == "register" else (entry._CONFIG, entry._CONFIG_NAME)
    expected = _hydra_help(capsys, monkeypatch, config_dir, name, overrides)
    assert app_help.print_help(config_dir, name, ["--help", *overrides])
    assert capsys.readouterr().out == expected
    assert len(expected.splitlines()) > 20


def test_only_help_and_overrides_are_answered():
    assert app_help.answers(["--help"]) and app_help.answers(["-h", "seed=1", "x=-1"])
    for argv in ([], ["seed=1"], ["--hydra-help"], ["--help", "--resolve"], ["--help", "-cd", "d"],
                 ["--help", "--cfg", "job"], ["--he"]):
        assert not app_help.answers(argv), argv


def test_a_failing_composition_is_left_to_hydra(capsys):
    register._register_schema()
    assert not app_help.print_help(register._CONFIG, "config", ["--help", "experiment=no_such_experiment"])
    assert capsys.readouterr().out == ""


def test_the_templates_fields_are_pythons():
    import string

    template = string.Template("$FLAGS_HELP ${CONFIG} $$HYDRA_CONFIG_GROUPS $$ $APP_CONFIG_GROUPS.")
    assert app_help._names(template) == {"FLAGS_HELP", "CONFIG", "APP_CONFIG_GROUPS"}
    if sys.version_info >= (3, 11):
        assert app_help._names(template) == set(template.get_identifiers())


def test_hydras_config_is_left_as_it_was():
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().cfg = None
    assert "num_train" in app_help.help_text(entry._CONFIG, entry._CONFIG_NAME, [])
    assert not HydraConfig.initialized()
