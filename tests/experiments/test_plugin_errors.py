"""A plug-in that misbehaves ends in one line naming it: a source whose ``check``, ``preflight`` or ``load``
raises, whose key clashes with another source's, a plug-in module that calls ``sys.exit`` at import."""
import sys
import textwrap

import pytest

import indreg
from indreg.experiments import config, register, sources
from indreg.experiments.errors import ConfigError

from experiment_helpers import compose

PLUGIN = textwrap.dedent('''
    from indreg.experiments.builtin_sources import phantom_data
    from indreg.experiments.sources import Source

    def load(cfg):
        raise KeyError("load boom")

    def check(cfg, require):
        raise RuntimeError("check boom")

    def preflight(cfg):
        raise KeyError("preflight boom")

    LOAD = Source("load_raises", load)
    CHECK = Source("check_raises", phantom_data, check=check)
    PREFLIGHT = Source("preflight_raises", phantom_data, preflight=preflight)
    CLASH = Source("clash", phantom_data, options=(("template", int, 3),))
''')


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    (tmp_path / "raising_source.py").write_text(PLUGIN)
    (tmp_path / "exiting_plugin.py").write_text("import sys\nsys.exit(3)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sources, "SOURCES", dict(sources.SOURCES))   # what a test registers goes with it
    yield
    for name in ("raising_source", "exiting_plugin"):
        sys.modules.pop(name, None)


def _cfg(source):
    return compose([f"data.source={source}", "phantom.size=16"])


def test_a_source_whose_check_raises_is_one_line_naming_it(plugin):
    with pytest.raises(ConfigError, match=r"^the data source 'check_raises': its check raised RuntimeError: check "
                                          r"boom$"):
        config.validate(_cfg("raising_source:CHECK"))


def test_a_source_whose_preflight_raises_is_one_line_naming_it(plugin):
    with pytest.raises(ConfigError, match=r"^the data source 'preflight_raises': its preflight raised KeyError: "
                                          r"'preflight boom'$"):
        sources.check_files(_cfg("raising_source:PREFLIGHT"))


def test_a_source_whose_load_raises_is_one_line_naming_it(plugin):
    with pytest.raises(ConfigError, match=r"^the data source 'load_raises': its load raised KeyError: 'load boom'$"):
        sources.load(_cfg("raising_source:LOAD"))


def test_a_source_key_that_clashes_is_one_line_naming_both(plugin, monkeypatch, capsys, tmp_path):
    import hydra

    monkeypatch.setattr(hydra, "main", lambda *a, **k: pytest.fail("Hydra started: the clash was not refused"))
    monkeypatch.setattr(sys, "argv", ["indreg-register", "data.source=raising_source:CLASH",
                                      f"hydra.run.dir={tmp_path / 'run'}"])
    with pytest.raises(SystemExit) as exc:   # the entry point, before Hydra
        register.main()
    lines = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 1 and len(lines) == 1 and "data.template is declared twice" in lines[0]
    with pytest.raises(ConfigError, match=r"^data\.template is declared twice with different types or defaults: by "
                                          r"source 'files' \(Optional\[str\], default None\) and by source 'clash' "
                                          r"\(int, default 3\); rename the plug-in's key$"):
        sources.data_fields()


def test_a_plugin_that_exits_at_import_is_a_message(plugin):
    with pytest.raises(ConfigError, match=r"data.source='exiting_plugin:SOURCE': cannot import it \(it called "
                                          r"sys.exit\(3\) at import\)$"):
        sources.get("exiting_plugin:SOURCE")
    with pytest.raises(ValueError, match=r"^model 'exiting_plugin:MODEL' cannot be imported: it called "
                                         r"sys.exit\(3\) at import$"):
        indreg.options.model("exiting_plugin:MODEL")


def test_built_in_sources_keep_their_own_errors():
    from indreg.io import DataFileError

    cfg = compose(["data=files", "data.template=/nonexistent/t.png", "data.sinogram=/nonexistent/s.npy",
                   "geometry=parallel", "geometry.angles=/nonexistent/a.tlt"])
    with pytest.raises(DataFileError):
        sources.check_files(cfg)
