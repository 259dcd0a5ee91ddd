"""What the entry points check before Hydra starts, and their one-line errors.

Hydra composes the config, creates the run directory and sets up logging before the task runs; whatever fails
on the way (a broken yaml file on the search path, a launcher whose plugin is not installed, a run directory
that cannot be created) would end in Hydra's traceback, some files already written. :func:`preflight` does the
same composition first and turns every such problem into one line ``<prog>: error: ...`` and exit status 1,
with nothing written.

Longer than 450 lines: every check before Hydra starts, for both apps, on one parser of the command line (the rerun
flag's guard, help, misspelt keys).
"""
from __future__ import annotations

import copy
import importlib.util
import os
import re
import string
import sys
from pathlib import Path

#: ``hydra/launcher=<name>`` -> (the extra of indreg that installs it, the plugin's module).
LAUNCHER_EXTRAS = {
    "joblib": ("joblib", "hydra_plugins.hydra_joblib_launcher"),
    "slurm": ("submitit", "hydra_plugins.hydra_submitit_launcher"),
    "submitit_slurm": ("submitit", "hydra_plugins.hydra_submitit_launcher"),
    "submitit_local": ("submitit", "hydra_plugins.hydra_submitit_launcher"),
    "ray": ("ray", "hydra_plugins.hydra_ray_launcher"),
    "ray_aws": ("ray", "hydra_plugins.hydra_ray_launcher"),
}

#: Hydra's flags that load a file as code: ``--experimental-rerun FILE`` unpickles FILE (a crafted file runs code).
#: Hydra's parser (argparse, ``allow_abbrev``) also takes every unambiguous prefix: ``--exp FILE``,
#: ``--experimental-r=FILE``. (``--config-dir`` / ``--config-path`` read yaml config files, which run no code.)
LOADING_FLAGS = ("--experimental-rerun",)
#: Where the documentation is: docs/ of indreg's source, rendered as a site by mkdocs (mkdocs.yml; the site is not
#: hosted yet); both ``--help``s name it.
DOCS_URL = "docs/index.md in indreg's source"

#: Flags of Hydra's that preflight checks the same as a plain run; any other flag (``--help``, ``--cfg``,
#: ``--info``, ``-cd``, ...) is Hydra's business alone.
_MULTIRUN_FLAGS = ("-m", "--multirun")
_RUN_FLAGS = ("-r", "--run")


class UsageError(Exception):
    """A problem with the command line or the config files; the message is the one line shown."""


def exit_error(prog: str, message: str) -> None:
    """``<prog>: error: <message>`` on stderr (one line), exit status 1."""
    print(f"{prog}: error: " + " ".join(str(message).split()), file=sys.stderr, flush=True)
    sys.exit(1)


def loading_flag(argv) -> str | None:
    """The first argument of ``argv`` that Hydra's parser would read as a flag of :data:`LOADING_FLAGS` (the flag
    or a prefix of it, ``--name`` or ``--name=value``), else ``None``."""
    for arg in argv:
        name = str(arg).split("=", 1)[0]
        if name.startswith("--") and len(name) > 2 and any(f.startswith(name) for f in LOADING_FLAGS):
            return str(arg)
    return None


def refuse_loading_flags(argv, prog: str) -> None:
    """Exit with one line (status 2, a usage error) if ``argv`` asks Hydra to load a file as code
    (:func:`loading_flag`): every entry point calls this before Hydra parses its command line."""
    arg = loading_flag(argv)
    if arg is None:
        return
    flag = next(f for f in LOADING_FLAGS if f.startswith(arg.split("=", 1)[0]))
    print(f"{prog}: error: {arg.split('=', 1)[0]} ({flag}) is not supported: it unpickles a file (a crafted file "
          "runs code), and indreg never writes one; rerun with the same overrides, or resume=true with the same "
          "run directory", file=sys.stderr, flush=True)
    sys.exit(2)


#: Keys of Hydra's own section whose values name a callable that Hydra imports and calls (``hydra.callbacks``,
#: factories of the logging config, plug-in targets): no command line sets them.
_CALLABLE_KEYS = ("_target_", "class", "()", "_partial_", "_args_")
#: A single path component (a file or directory name): letters, digits, '.', '_' and '-', not starting with '.'.
_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")


def _one_name(value, dot_ok: bool = False) -> bool:
    """``value`` is one path component (no separator, not ``.`` or ``..``, no interpolation)."""
    v = str(value)
    return (bool(v) and set(v) <= _NAME_CHARS and v not in (".", "..")
            and (dot_ok or not v.startswith(".")))


def _leaves(key: str, value):
    """``(key, value)`` for every leaf of an override's value (``hydra={job: {name: x}}`` -> ``hydra.job.name``)."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(f"{key}.{k}", v)
    else:
        yield key, value


def hydra_override_problem(key: str, value) -> str | None:
    """Why the override ``key=value`` of Hydra's own section is refused (it would run code or write outside the run
    directory), else ``None``."""
    parts = key.replace("/", ".").split(".")
    if len(parts) > 1 and parts[1] == "callbacks":
        return "Hydra's callbacks import and call what they name (code run by the command line); indreg has none"
    if parts[-1] in _CALLABLE_KEYS:
        return "it names a callable that Hydra would import and call (code run by the command line)"
    if parts[1:] in (["job_logging"], ["hydra_logging"]) and "/" not in key:   # hydra/job_logging=<shipped option>
        return None
    if len(parts) > 2 and parts[1] in ("job_logging", "hydra_logging") and parts[-1] in ("filename", "stream"):
        return "the log is written in the run directory (<run dir>/<hydra.job.name>.log)"
    if key == "hydra.job.name" and not _one_name(value):
        return ("the job's name names its log file in the run directory: letters, digits, '.', '_' and '-', "
                "not starting with '.'")
    if key == "hydra.output_subdir" and value is not None and not _one_name(value, dot_ok=True):
        return "Hydra's config copy goes into a subdirectory of the run directory: one name (default .hydra) or null"
    parts_of_value = str(value).replace("\\", "/").split("/")
    if key == "hydra.sweep.subdir" and (parts_of_value[0] == "" or ".." in parts_of_value):
        return "a job's directory lies inside hydra.sweep.dir: a relative name without '..'"
    return None


def hydra_override(argv) -> tuple | None:
    """The first override of ``argv`` (as Hydra's parsers read the command line, sweeps' values each) that sets
    Hydra's own section so that it would run code or write outside the run directory:
    ``(argument, key, value, why)``, else ``None``. (A command line Hydra cannot parse is left to Hydra.)"""
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        args, _ = get_args_parser().parse_known_args([str(a) for a in argv])
    except SystemExit:   # Hydra's parser refuses it (an ambiguous flag): Hydra ends it alike
        return None
    parser = OverridesParser.create()
    for arg in args.overrides:
        try:
            o = parser.parse_override(arg)
        except HydraException:
            continue
        key, package = o.key_or_group, (o.package or "").replace("_global_.", "").replace("_global_", "")
        if package.startswith("hydra"):
            return arg, f"{key}@{package}", None, "it places a config into Hydra's own section"
        if not (key == "hydra" or key.startswith(("hydra.", "hydra/"))):
            continue
        values = list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.value()]
        for value in values:
            for k, v in _leaves(key, value):
                why = hydra_override_problem(k, v)
                if why:
                    return arg, k, v, why
    return None


def refuse_hydra_overrides(argv, prog: str) -> None:
    """Exit with one line (status 2) if an override of ``argv`` sets Hydra's own section so that it would run code
    or write outside the run directory (:func:`hydra_override`)."""
    found = hydra_override(argv)
    if found is not None:
        arg, key, value, why = found
        print(f"{prog}: error: {arg}: {key} is not accepted: {why}", file=sys.stderr, flush=True)
        sys.exit(2)


def guard(argv, prog: str) -> None:
    """What every entry point checks first, whatever the flags (``--help`` included): no flag that loads a file as
    code (:func:`refuse_loading_flags`) and no override of Hydra's section that runs code or writes outside the
    run directory (:func:`refuse_hydra_overrides`); a problem exits with one line, status 2."""
    refuse_loading_flags(argv, prog)
    refuse_hydra_overrides(argv, prog)


def error_chain(exc: BaseException) -> str:
    """The messages of an exception and its causes, in one line."""
    parts, e = [], exc
    while e is not None:
        parts.append(" ".join(str(e).split()))
        e = e.__cause__ or (None if e.__suppress_context__ else e.__context__)   # as Python's tracebacks
    return ": ".join(p for p in dict.fromkeys(parts) if p)


def _key(override: str) -> str:
    """The key of an override: ``+solver.foo=1`` -> ``solver.foo``, ``hydra/launcher=joblib`` -> ``hydra/launcher``."""
    return override.split("=", 1)[0].lstrip("+~")


def _plugin_installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def check_launcher(overrides) -> None:
    """A ``hydra/launcher=<name>`` whose plugin is missing names the extra that installs it."""
    for o in overrides:
        if _key(o) != "hydra/launcher" or "=" not in o:
            continue
        name = o.split("=", 1)[1]
        if name in LAUNCHER_EXTRAS:
            extra, module = LAUNCHER_EXTRAS[name]
            if not _plugin_installed(module):
                raise UsageError(f"hydra/launcher={name} needs its Hydra plugin, which is not installed: "
                                 f"pip install \"indreg[{extra}]\"")


def check_keys(overrides, base, prog: str) -> None:
    """Overrides of an app without config groups or schema may only set the keys of its config ``base`` (a
    key it does not read would be ignored)."""
    for o in overrides:
        key = _key(o)
        if key.startswith(("hydra.", "hydra/")):
            continue
        if o.startswith("~"):
            raise UsageError(f"{o}: {prog} needs every key of its config; set a value instead")
        node, path = base, []
        for part in key.replace("/", ".").split("."):
            if not hasattr(node, "keys") or part not in node:
                where = f"'{'.'.join(path)}'" if path else prog
                known = ", ".join(node.keys()) if hasattr(node, "keys") else "none (it is a value)"
                from .errors import did_you_mean, dotted_keys
                hint = did_you_mean(key, dotted_keys(base))
                raise UsageError(f"{o}: {prog} has no key '{key}'{f' ({hint})' if hint else ''}; the keys of {where} "
                                 f"are {known} (see {prog} --help)")
            node, path = node[part], path + [part]


def check_writable_dir(key: str, path) -> None:
    """``path`` (a directory to be created or written) can be: its nearest existing ancestor is a writable
    directory. Writes nothing."""
    p = Path(os.path.abspath(path))
    existing = p
    while not os.path.lexists(existing):
        existing = existing.parent
    if not existing.is_dir():
        raise UsageError(f"{key}={path} cannot be created: {existing} is not a directory")
    if not os.access(existing, os.W_OK | os.X_OK):
        what = "the run directory" if existing == p else f"{existing}, where it would be created,"
        raise UsageError(f"{key}={path} is not writable: {what} is read-only for this user; choose another {key}")


def check_links(key: str, path) -> None:
    """``path`` (an existing run or sweep directory) holds no symbolic link: Hydra (its ``.hydra/`` files, the
    log) and the app would write through one (``indreg._outfiles``)."""
    from .._outfiles import LinkError, check_no_links

    try:
        check_no_links(path, remedy=f"choose another {key}")
    except LinkError as e:
        raise UsageError(str(e)) from None


def _split_sweeps(overrides) -> list:
    """The overrides without sweeps (``a=1,2``, ``range(...)``, ...): a multirun's common config."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(list(overrides))
    return [o.input_line for o in parsed if not o.is_sweep_override()]


def compose(config_dir, config_name: str, overrides):
    """The config of ``config_name`` with ``overrides`` (Hydra's section ``hydra`` included)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(config_dir), job_name="preflight"):
            return hydra_compose(config_name, overrides=list(overrides), return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()


def job_config(cfg):
    """``cfg`` without Hydra's section: what the task receives."""
    from omegaconf import open_dict, read_write

    job = copy.deepcopy(cfg)
    with read_write(job), open_dict(job):
        del job["hydra"]
    return job


def preflight(argv, prog: str, config_dir, config_name: str, validate=None, base=None) -> None:
    """Check a command line before Hydra sees it; a problem ends in ``<prog>: error: ...``, exit status 1.

    Checked: the launcher's plugin (``hydra/launcher=joblib`` without ``indreg[joblib]`` names the extra), the
    keys of an app without config groups (``base``, its config), the composition (a broken yaml file, an unknown
    group or option, ``hydra.searchpath`` included), the job's config (``validate``; a multirun's sweeps are
    left to its jobs) and the run directory (``hydra.run.dir``, or ``hydra.sweep.dir`` with ``-m``): it must be
    creatable and writable and hold no symbolic link. Hydra's other flags (``--help``, ``--cfg``, ...) skip the checks.
    """
    flags = [a for a in argv if a.startswith("-")]
    if any(f not in _MULTIRUN_FLAGS + _RUN_FLAGS for f in flags):
        return
    multirun = any(f in _MULTIRUN_FLAGS for f in flags)
    overrides = [a for a in argv if not a.startswith("-")]
    try:
        check_launcher(overrides)
        if base is not None:
            check_keys(overrides, base, prog)
        cfg = _compose_or_fail(config_dir, config_name, _split_sweeps(overrides) if multirun else overrides)
        check_hydra_section(cfg)
        if validate is not None and not multirun:
            validate(job_config(cfg))
        key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
        check_writable_dir(key, _resolved(cfg, key))
        check_links(key, _resolved(cfg, key))
    except UsageError as e:
        exit_error(prog, str(e))
    except ValueError as e:  # the app's ConfigError (a ValueError naming the key)
        exit_error(prog, error_chain(e))


def check_hydra_section(cfg) -> None:
    """The composed config's Hydra section (configs on ``hydra.searchpath`` included) has no callbacks and keeps
    Hydra's files in the run directory (:func:`hydra_override_problem`)."""
    from omegaconf import OmegaConf

    section = OmegaConf.to_container(cfg.hydra, resolve=False)
    for key in ("callbacks", "output_subdir"):
        value = section.get(key)
        for k, v in _leaves(f"hydra.{key}", value) if value else ():
            why = hydra_override_problem(k, v)
            if why:
                raise UsageError(f"{k}={v} (from the composed config) is not accepted: {why}")


def _compose_or_fail(config_dir, config_name, overrides):
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException
    from yaml import YAMLError

    try:
        return compose(config_dir, config_name, overrides)
    except (HydraException, OmegaConfBaseException, YAMLError, ValueError) as e:
        raise UsageError(misspelt_key(e, config_dir, config_name, overrides) or error_chain(e)) from None


#: Hydra's message for an override of a key the config does not have (its hint, ``+key=value``, would add the
#: misspelt key, which the app then refuses).
_NO_KEY = re.compile(r"Could not override '([^']+)'\.\s*To append to your config use")


def misspelt_key(error: BaseException, config_dir, config_name: str, overrides) -> str | None:
    """For Hydra's "Could not override 'data.templat'" (a key the config lacks): one line naming the valid key
    nearest to it (``indreg.experiments.errors.nearest_key``, among the keys of the config composed without that
    override), in place of Hydra's hint to append the misspelt key with ``+``; None for any other error."""
    from .errors import dotted_keys, nearest_key

    match = _NO_KEY.search(error_chain(error))
    if match is None:
        return None
    key = match.group(1)
    given = next((o for o in overrides if _key(o) == key), key)
    try:
        cfg = compose(config_dir, config_name, [o for o in overrides if _key(o) != key])
    except Exception:   # noqa: BLE001 (another bad override: Hydra's own message then)
        return None
    near = nearest_key(key, [k for k in dotted_keys(cfg) if not k.startswith("hydra")])
    value = given.split("=", 1)[1] if "=" in given else ""
    hint = f"; did you mean {near}={value}?" if near else "; --help lists the keys"
    return f"{given}: the config has no key {key}{hint}"


def _resolved(cfg, key: str) -> str:
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        return str(OmegaConf.select(cfg, key, throw_on_missing=True))
    except OmegaConfBaseException as e:
        raise UsageError(f"{key}: {error_chain(e)}") from None


# ---------------------------------------------------------------------------------------------------- --help
# ``--help`` of the Hydra apps, composed once: the same text as Hydra's own ``--help``, in a fraction of its time.
# Hydra's ``--help`` fills all four fields of its help template (``$FLAGS_HELP``, ``$HYDRA_CONFIG_GROUPS``,
# ``$APP_CONFIG_GROUPS``, ``$CONFIG``) whatever the template uses, and lists the config groups with a fresh deep copy
# of its config repository (its ConfigStore included) for every group: about 100 copies, most of the CPU seconds of
# ``indreg-register --help``. :func:`help_text` composes the config as Hydra does, fills only the fields the app's
# template (``hydra.help.template``) names, and lists the groups from one repository.

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
