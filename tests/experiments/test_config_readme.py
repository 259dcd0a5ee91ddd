"""configs/README.md is generated from the option table: the committed file is what the table gives (CI's check)."""
from indreg.experiments import config_readme


def test_committed_config_readme_is_the_generated_one():
    assert config_readme.README.read_text() == config_readme.markdown(), \
        "configs/README.md is stale: run python -m indreg.experiments.config_readme"
    assert config_readme.main(["--check"]) == 0


def test_config_readme_cells_are_short_and_every_key_has_a_row():
    from indreg import options

    text = config_readme.markdown()
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert max(len(cell) for row in rows for cell in row.replace("\\|", "").split("|")) <= 300
    listed = config_readme.listed_options()
    assert {o.name for o in options.CORE if o.group != "run"} <= {o.name for o in listed}
    for o in listed:
        assert f"| `{o.config_key}` |" in text


def test_a_plug_in_registered_in_the_process_is_not_listed(monkeypatch):
    """Tests register plug-in models and solvers: the generated file lists indreg's own keys only."""
    from indreg import options

    plugin = options.Model("plugged", lambda *a: None, options=(
        options.Option("plugged_key", "deformation", "plugged_key", 1, options.number(), "x", int,
                       models=("plugged",)),))
    monkeypatch.setitem(options.MODELS, "plugged", plugin)
    assert "plugged_key" not in config_readme.markdown()
    assert config_readme.main(["--check"]) == 0
