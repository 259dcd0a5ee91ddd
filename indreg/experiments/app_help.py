"""``--help`` of the Hydra apps, composed once: the same text as Hydra's own ``--help``, in a fraction of its time.

Hydra's ``--help`` fills all four fields of its help template (``$FLAGS_HELP``, ``$HYDRA_CONFIG_GROUPS``,
``$APP_CONFIG_GROUPS``, ``$CONFIG``) whatever the template uses, and lists the config groups with a fresh deep copy
of its config repository (its ConfigStore included) for every group: about 100 copies, most of the CPU seconds of
``indreg-register --help``. :func:`help_text` composes the config as Hydra does, fills only the fields the app's
template (``hydra.help.template``) names, and lists the groups from one repository. tests/experiments/test_app_help.py
checks the text against Hydra's own for both apps.
"""
from __future__ import annotations

import copy
import string
from pathlib import Path

__all__ = ["HELP_FLAGS", "answers", "help_text", "print_help"]

#: Hydra's flags for the app's help (``--hydra-help``, Hydra's own, is left to Hydra).
HELP_FLAGS = ("--help", "-h")


def answers(argv) -> bool:
    """Whether :func:`print_help` answers ``argv``: a help flag, every other argument an override (any other flag,
    ``--config-dir``, ``--resolve``, ..., goes to Hydra)."""
    return any(a in HELP_FLAGS for a in argv) and all(a in HELP_FLAGS or not a.startswith("-") for a in argv)


def _groups(repository, parent: str = "") -> list:
    """Every config group below ``parent`` that has options (as Hydra's ``list_all_config_groups``)."""
    from hydra.core.object_type import ObjectType

    found = []
    for child in repository.get_group_options(parent, ObjectType.GROUP):
        group = f"{parent}/{child}" if parent else child
        if repository.get_group_options(group, ObjectType.CONFIG):
            found.append(group)
        if repository.get_group_options(group, ObjectType.GROUP):
            found += _groups(repository, group)
    return found


def _format_groups(repository, hydra_groups: bool) -> str:
    """``group: option, option`` per line, sorted: Hydra's own groups or the app's (as Hydra's
    ``format_config_groups``)."""
    def is_hydra(group: str) -> bool:
        return group.startswith("hydra/") or group == "hydra"

    groups = sorted(g for g in _groups(repository) if is_hydra(g) == hydra_groups)
    return "".join(f"{g}: {', '.join(sorted(repository.get_group_options(g)))}\n" for g in groups)


def _fields(names, hydra, cfg) -> dict:
    """The template's fields among Hydra's four, each computed only if named."""
    from hydra._internal.utils import get_args_parser
    from omegaconf import OmegaConf

    makers = {"FLAGS_HELP": lambda: hydra.format_args_help(get_args_parser()),
              "HYDRA_CONFIG_GROUPS": lambda: _format_groups(hydra.config_loader.repository, True),
              "APP_CONFIG_GROUPS": lambda: _format_groups(hydra.config_loader.repository, False),
              "CONFIG": lambda: OmegaConf.to_yaml(hydra.get_sanitized_cfg(copy.deepcopy(cfg), "job"))}
    return {name: makers[name]() for name in names if name in makers}


def help_text(config_dir: str | Path, config_name: str, overrides) -> str:
    """The text Hydra's ``--help`` prints for the app of ``config_name`` in ``config_dir`` with ``overrides``."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    previous = HydraConfig.instance().cfg
    with initialize_config_dir(version_base="1.3", config_dir=str(config_dir), job_name=config_name):
        hydra = GlobalHydra.instance().hydra
        cfg = hydra.compose_config(config_name, list(overrides), run_mode=RunMode.RUN)
        HydraConfig.instance().set_config(cfg)   # as Hydra's --help: ${hydra:...} resolves in the template
        try:
            template = string.Template(cfg.hydra.help.template)
            return template.substitute(_fields(_names(template), hydra, cfg))
        finally:
            HydraConfig.instance().cfg = previous


def _names(template: string.Template) -> set:
    """The fields ``$NAME`` / ``${NAME}`` of ``template`` (``Template.get_identifiers`` of Python 3.11)."""
    return {m["named"] or m["braced"] for m in template.pattern.finditer(template.template)} - {None}


def print_help(config_dir: str | Path, config_name: str, argv) -> bool:
    """Print the help for ``argv`` (:func:`answers`) and return True; False, with nothing printed, if composing it
    fails: Hydra's ``--help`` then reports the problem as it does."""
    try:
        text = help_text(config_dir, config_name, [a for a in argv if a not in HELP_FLAGS])
    except Exception:   # noqa: BLE001 -- any failure is Hydra's to report, in Hydra's words
        return False
    print(text)
    return True
