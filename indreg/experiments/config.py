"""Typed (structured) configs of the experiment app, registered in Hydra's ConfigStore, and their validation.

The dataclasses of :mod:`indreg.experiments.schema` are the *schema* of ``indreg/conf/**.yaml``: Hydra merges
every yaml file into them, so an
unknown key (``solver.gama=1``), a wrong type (``solver.gamma=abc``) or a value outside an enum
(``deformation.action=affine``, ``phantom.target=cat``) fails at composition with a message that names the key.
Range checks that a type cannot express (``solver.gamma >= 0``, ``kernel.sigma > 0``, ...) are done by
:func:`validate` when the app starts, also naming the key.

Config groups (one sub-config each) and top-level keys::

    data         where template and data come from: ``phantom`` (simulated, the default) or ``files``
    phantom      template/target names (``indreg.phantoms.get``) and the grid size n (domain [-16, 16]^2)
    geometry     parallel- or fan-beam geometry: angles x detector bins (the authors' ODL partition by default)
    noise        white noise at an SNR in dB ("code" convention, docs/paper_notes.md) or with a fixed std
    deformation  LDDMM time steps N, group action, backward (gradient) scheme, interpolation scheme
    kernel       Gaussian RKHS kernel width sigma
    solver       gamma, step size, iterations; Algorithm 1 or a torch.optim parametrisation
    baseline     FBP (filter, frequency scaling) and TV (mu, iterations) reconstructions from the same data
    logging      evaluation / image / checkpoint period k, TensorBoard, progress bar, figure
    validation   held-out angles (``holdout``) and early stopping (``patience``)
    experiment   presets of the paper's test suites (package _global_), ``suite1_jv`` by default
    sweep        multirun presets (``sweep=suite3_table``: the paper's sensitivity table)
    name, seed, dtype, device, resume, stop_after

The yaml files live in the package (``indreg/conf``, :data:`CONFIG_DIR`), so an installed wheel composes exactly
the configs of the checkout.
"""
from __future__ import annotations

import re
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from .. import options as _options
from .._checks import is_finite_number
from ..conf import CONFIG_DIR  # noqa: F401  (re-exported: indreg.experiments.config.CONFIG_DIR)
from . import sources
from .errors import ConfigError   # re-exported: ``from indreg.experiments.config import ConfigError``
from .errors import did_you_mean, dotted_keys
from .schema import build_schema

#: The schema of the built-in models and sources (``schema.build_schema``; :func:`register_schema` rebuilds it).
RegisterConfig = build_schema()


SCHEMA_NAME = "indreg_schema"

# The app's yaml configs (``indreg.conf.CONFIG_DIR``, re-exported here): users add their own config groups or
# presets with Hydra's search path, e.g. ``indreg-register 'hydra.searchpath=[file:///my/configs]' ...``.


#: Example data shipped with the package, named in configs as ``${indreg_data:<file name>}``.
DATA_DIR = Path(__file__).resolve().parents[1] / "data"


def register_schema(argv=()) -> None:
    """Store the schema ``indreg_schema`` (``RegisterConfig``) that ``conf/config.yaml`` starts from, and the
    resolvers (``${indreg_data:name}``: the path of a file shipped in ``indreg/data``). The plug-in models and
    solvers named in the command line ``argv`` (``deformation.model=module:attribute``, ``solver.name=...``) are
    imported first, and the modules of ``plugins=[module, ...]`` (a correction's), so that their options are config
    keys (``deformation.my_option=3``)."""
    from hydra.core.config_store import ConfigStore

    global RegisterConfig
    if import_plugins(argv):
        RegisterConfig = build_schema()
    ConfigStore.instance().store(name=SCHEMA_NAME, node=RegisterConfig)
    register_resolvers()


def import_plugins(argv) -> bool:
    """Import the model, the solver and the data source named ``module:attribute`` in the overrides ``argv``
    (``deformation.model=...``, ``solver.name=...``, ``data.source=...``), the working directory on ``sys.path`` as with ``python -m``
    (console scripts leave it off). Returns whether one brought keys of its own; an import error is left to the
    config's validation, which names the key."""
    import sys

    given = dict(a.lstrip("+~").split("=", 1) for a in argv if "=" in a)
    model, solver, source = (given.get(key, "") for key in ("deformation.model", "solver.name", "data.source"))
    model, solver, source = (model if ":" in model and model not in _options.MODELS else None,
                             solver if ":" in solver and solver not in _options.SOLVERS else None,
                             source if ":" in source and source not in sources.SOURCES else None)
    modules = [m.strip(" '\"") for m in given.get("plugins", "").strip("[]").split(",") if m.strip(" '\"")]
    if (model or solver or source or modules) and "" not in sys.path and "." not in sys.path:
        sys.path.append("")
    try:
        new = _import_modules(modules)
    except ConfigError:   # reported by the config's validation, which names the key
        new = False
    for name, find in ((model, _options.model), (solver, _options.solver)):
        try:
            if name:
                find(name)
                new = True
        except ValueError:
            pass
    try:
        if source and sources.get(source).options:
            new = True
    except (ValueError, ConfigError):
        pass
    return new


def _import_modules(modules) -> bool:
    """Import the modules of ``plugins``; raises :class:`ConfigError` naming the key for one that cannot be."""
    import importlib

    for name in modules:
        try:
            importlib.import_module(name)
        except Exception as e:   # a syntax error or an exception at import: one line
            raise ConfigError(f"invalid config value plugins={list(modules)!r}: {name!r} cannot be imported: "
                              f"{type(e).__name__}: {e}") from None
    return bool(modules)


_DEVICE = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")
_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]*")  # a single path component (it names the run dir)


def _require(ok: bool, key: str, expected: str, value) -> None:
    if not ok:
        raise ConfigError(f"invalid config value {key}={value!r}: expected {expected}")



def _unknown_keys(node, schema, prefix: str = "") -> list:
    """Dotted keys of ``node`` absent from ``schema`` (e.g. added with Hydra's ``+key=value``)."""
    out = []
    for key in node:
        if key not in schema:
            out.append(prefix + str(key))
        elif OmegaConf.is_dict(schema[key]) and key != "optimizer_kwargs":
            out += _unknown_keys(node[key], schema[key], f"{prefix}{key}.")
    return out


def validate(cfg: DictConfig, registration: bool = True) -> None:
    """Range checks the schema's types cannot express; raises :class:`ConfigError` naming the key. ``registration``
    False leaves the registration options to ``indreg.registration.run.setup`` (the run resolves them there once, with the same
    messages)."""
    c = cfg
    schema = OmegaConf.structured(RegisterConfig)
    unknown = _unknown_keys(cfg, schema)
    if unknown:
        hints = "; ".join(f"{k}: {hint}" for k in unknown if (hint := did_you_mean(k, dotted_keys(schema))))
        raise ConfigError(f"unknown config key(s) {', '.join(unknown)}: not in the schema "
                          "indreg.experiments.config.RegisterConfig" + (f" ({hints})" if hints else ""))
    _import_modules(c.plugins)
    _require(bool(_NAME.fullmatch(c.name)), "name", "letters, digits, '.', '_' and '-', not starting with '.'",
             c.name)
    _require(0 <= c.seed < 2 ** 32, "seed", "an integer in [0, 2**32) (numpy's seed range)", c.seed)
    _require(bool(_DEVICE.match(c.device)), "device", "'auto', 'cpu', 'cuda' or 'cuda:<index>'", c.device)
    _check_cuda(c.device)
    _require(c.stop_after is None or c.stop_after >= 0, "stop_after", "null or an integer >= 0", c.stop_after)
    _require(c.phantom.size >= 7, "phantom.size", "an integer >= 7 (the SSIM window)", c.phantom.size)
    _require(c.phantom.ndim in (2, 3), "phantom.ndim", "2 (images) or 3 (volumes)", c.phantom.ndim)
    _require(c.phantom.thickness is None or (c.phantom.ndim == 3 and 7 <= c.phantom.thickness <= c.phantom.size),
             "phantom.thickness", "null or, for volumes (phantom.ndim=3), an integer in [7, phantom.size] (7: the "
             "SSIM window)", c.phantom.thickness)
    _require(c.phantom.rows is None or (c.phantom.ndim == 3 and 7 <= c.phantom.rows <= c.phantom.size),
             "phantom.rows", "null or, for volumes (phantom.ndim=3), an integer in [7, phantom.size] (7: the SSIM "
             "window)", c.phantom.rows)
    _require(is_finite_number(c.phantom.half_width) and c.phantom.half_width > 0, "phantom.half_width", "a number > 0",
             c.phantom.half_width)
    _validate_data(c)
    n = c.noise
    _require(n.snr_db is None or n.std is None, "noise.snr_db", "at most one of noise.snr_db and noise.std",
             (n.snr_db, n.std))
    _require(n.snr_db is None or (is_finite_number(n.snr_db) and abs(n.snr_db) <= 300), "noise.snr_db",
             "a number in [-300, 300] (dB) or null", n.snr_db)
    _require(n.std is None or (is_finite_number(n.std) and n.std >= 0), "noise.std", "a number >= 0 or null", n.std)
    _require(n.seed is None or 0 <= n.seed < 2 ** 32, "noise.seed", "null or an integer in [0, 2**32)", n.seed)
    if registration:
        check_registration(c)
    b = c.baseline
    _require(is_finite_number(b.fbp_frequency_scaling) and 0 < b.fbp_frequency_scaling <= 1, "baseline.fbp_frequency_scaling",
             "a number in (0, 1]", b.fbp_frequency_scaling)
    _require(is_finite_number(b.tv_mu) and b.tv_mu >= 0, "baseline.tv_mu", "a number >= 0", b.tv_mu)
    _require(b.tv_iterations >= 1, "baseline.tv_iterations", "an integer >= 1", b.tv_iterations)
    _require(b.sirt_iterations >= 1, "baseline.sirt_iterations", "an integer >= 1", b.sirt_iterations)
    lg = c.logging
    _require(lg.every >= 1, "logging.every", "an integer >= 1", lg.every)
    _require(lg.checkpoint_every >= 1, "logging.checkpoint_every", "an integer >= 1", lg.checkpoint_every)


def registration_values(cfg: DictConfig) -> dict:
    """The ``indreg.register`` options of the config's ``kernel``, ``deformation`` and ``solver`` groups
    (``solver.name=torch_optim`` names its optimizer in ``solver.optimizer``)."""
    plain = to_plain(cfg)
    values = {o.name: plain[o.group][o.key] for o in _options.all_options() if o.key in plain.get(o.group, {})}
    if values["solver"] == "torch_optim":
        values["solver"] = plain["solver"]["optimizer"]
    return values


def check_registration(cfg: DictConfig) -> dict:
    """``indreg.options.resolve`` on the config's values (options of another solver / model are dropped);
    errors name the config key."""
    try:
        return _options.resolve(registration_values(cfg), label=lambda o: o.config_key, strict=False)
    except _options.OptionError as e:
        raise ConfigError(f"invalid config value {e.label}={e.value!r}: expected {e.expected}") from None


def _validate_data(c: DictConfig) -> None:
    """The ``data`` and ``geometry`` groups (which keys a source needs is its own business, checked here)."""
    d, g = c.data, c.geometry
    source = sources.get(d.source)
    if source.check is not None:   # the source's own keys (and what it needs of the geometry)
        with sources.calling(source, "check"):
            source.check(c, _require)
    _require((g.det_min is None) == (g.det_max is None), "geometry.det_min",
             "both det_min and det_max, or neither (fitted to the domain)", (g.det_min, g.det_max))
    if g.det_min is not None:
        _require(is_finite_number(g.det_min) and is_finite_number(g.det_max) and g.det_min < g.det_max, "geometry.det_min",
                 "finite det_min < det_max", (g.det_min, g.det_max))
    if g.kind.value == "tilt_series":
        _require(is_finite_number(g.tilt_step) and g.tilt_step > 0, "geometry.tilt_step", "a number > 0", g.tilt_step)
        _require(is_finite_number(g.tilt_min) and is_finite_number(g.tilt_max) and g.tilt_min <= g.tilt_max, "geometry.tilt_min",
                 "finite tilt_min <= tilt_max", (g.tilt_min, g.tilt_max))
    _require(g.tilt_axis_angle is None or (is_finite_number(g.tilt_axis_angle) and abs(g.tilt_axis_angle) <= 180),
             "geometry.tilt_axis_angle", "a finite number of degrees in [-180, 180] or null", g.tilt_axis_angle)
    _require(g.tilt_axis_angle is None or g.kind.value == "tilt_series", "geometry.tilt_axis_angle",
             "null except for a measured tilt series (data=files geometry=tilt_series)", g.tilt_axis_angle)
    if g.kind.value == "fan_flat":
        _require(is_finite_number(g.src_radius) and g.src_radius > 0, "geometry.src_radius",
                 "a number > 0 (source to origin) for geometry.kind=fan_flat", g.src_radius)
    _require(is_finite_number(g.det_radius) and g.det_radius >= 0, "geometry.det_radius", "a number >= 0", g.det_radius)


def _check_cuda(device: str) -> None:
    """``device=cuda[:i]`` needs a CUDA device (with that index)."""
    if not device.startswith("cuda"):
        return
    import torch

    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    index = int(device.split(":")[1]) if ":" in device else 0
    _require(index < count, "device", f"'auto', 'cpu' or a CUDA device of this machine ({count} CUDA device(s) "
             "available)", device)


def path_component(name) -> str:
    """``name`` as one safe path component (resolver ``indreg_path``, used in the run-dir templates): anything
    but letters, digits, ``._-`` becomes ``_`` and a leading ``.`` is dropped, so ``name=../../x`` cannot place
    Hydra's run dir outside ``outputs/``; ``validate`` then refuses the name itself."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", str(name)).lstrip(".")
    return safe or "_"


def run_dir_name(name, model) -> str:
    """The run directory's name (resolver ``indreg_run_dir``): ``name`` as a path component (``path_component``),
    with ``-<model>`` appended for a model other than LDDMM that the name does not mention, so that e.g.
    ``experiment=suite4_missing_object deformation=metamorphosis`` is not filed in the LDDMM run's folder."""
    short = str(getattr(model, "value", model)).rpartition(":")[2]
    base = path_component(name)
    return base if short in ("", "lddmm") or short in base else path_component(f"{base}-{short}")


def register_resolvers() -> None:
    OmegaConf.register_new_resolver("indreg_path", path_component, replace=True)
    OmegaConf.register_new_resolver("indreg_run_dir", run_dir_name, replace=True)
    OmegaConf.register_new_resolver("indreg_data", lambda name: str(DATA_DIR / name), replace=True)
    OmegaConf.register_new_resolver("indreg_simulated", simulated_only, replace=True)
    OmegaConf.register_new_resolver("indreg_run_name", run_name, replace=True)


def run_name(source: str, model: str) -> str:
    """The default experiment's run name: ``suite1_jv``, or named after a plug-in (``module:attribute``) data
    source (its attribute) and model (``-`` and its attribute), so that a plug-in's runs are not filed as suite 1's."""
    base = source.rpartition(":")[2] if ":" in source else "suite1_jv"
    return base + (f"-{model.rpartition(':')[2]}" if ":" in model else "")


def simulated_only(source: str, value):
    """``value`` for a simulated data source (a preset's absolute weight on its own data), None for measured
    data (``Source.measured``, e.g. ``data=files``: the relative form applies, ``indreg.units``)."""
    return None if sources.is_measured(source) else value


def to_plain(cfg: DictConfig) -> dict:
    """The config as plain python (enums as strings), e.g. for metrics.json and checkpoints."""
    return OmegaConf.to_container(cfg, resolve=True, enum_to_str=True)
