"""Data sources of the experiment app: where the template, the data and the forward operator come from.

``data.source`` names a :class:`Source` (:func:`get`): a function ``load(cfg) -> Data`` with the ``data`` group's
keys it reads (``options``, each declared by its source: the app's schema is built from them) and a check of their
values. Built in (:mod:`indreg.experiments.builtin_sources`, registered when the app's schema is imported):

    phantom   the paper's suites: ``indreg.phantoms`` template and target, data ``T(target)`` plus white noise
    dynamic   a breathing Shepp-Logan phantom measured a few angles at a time (``indreg.dynamic``): data of
              ``data.frames`` time points for ``deformation=spatiotemporal`` (docs/spatiotemporal.md)
    files     your own data: ``indreg.load`` (:mod:`indreg.inputs`) with the config's ``data`` and ``geometry``
              values: template, sinogram (and optionally a target) read by ``indreg.io``; with
              ``geometry=tilt_series`` a template volume and an MRC tilt series with its .tlt angles
    NAME      an entry point ``NAME = "my_package.my_module:my_source"`` of the group ``indreg.sources`` (in the
              ``[project.entry-points."indreg.sources"]`` table of your package's pyproject.toml)
    my_package.my_module:my_source
              any importable ``module:attribute``, no installation needed (the module on ``sys.path`` /
              ``PYTHONPATH`` or in the working directory): a :class:`Source` (with keys of its own:
              ``data.my_key=...``) or a plain function ``cfg -> Data``

The contract of a source's ``load``: it gets the composed, validated config (``cfg.data.<its keys>``, the
``geometry`` group, ``cfg.seed``, ...) and returns a :class:`Data` record, or what ``indreg.load`` returns (a
``RegistrationInputs``, e.g. ``return indreg.load(my_template, my_data, ...)``). Invalid input raises one line
before any computation: ``indreg.io.DataFileError`` (a file), :class:`~indreg.experiments.errors.ConfigError`
(a config value) or ``ValueError`` (shown as an invalid configuration). The run loop only sees :class:`Data`, so a
new source is one function and, for keys of its own, one :class:`Source`.

Convention: images ``(n, n)`` (or volumes ``(nx, ny, nz)``) float64 on the CPU, axis 0 = x, on
``[-half_width, half_width]^d`` (square / cubic cells); data ``operator.range_shape``: ``(num_angles, det_count)``
(a tilt series: ``(num_tilts, det_rows, det_cols)``) float64 on the CPU.
"""
from __future__ import annotations

import importlib
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Optional

from omegaconf import DictConfig

from ..io._files import DataFileError
from ..domain import ImageDomain
from ..options import add_to_registry
from .errors import ConfigError

if TYPE_CHECKING:   # imported where used: the app's preflight checks a source's config without torch
    import torch

    from ..inputs import RegistrationInputs

__all__ = ["Data", "Source", "SOURCES", "register_source", "get", "resolve", "load", "data_fields", "check_files",
           "describe", "is_measured"]

#: The entry-point group of installed sources (``data.source=<entry point name>``).
ENTRY_POINTS = "indreg.sources"
#: The registered sources by name (:func:`register_source`; the built-ins, then plug-ins named on the command line).
SOURCES: dict = {}


@dataclass
class Data:
    """What a source provides (float64, CPU). ``target_64`` / ``clean_64`` / ``snr_db`` are ``None`` when
    unknown (measured data). ``label``: a short name of the template for hparams and titles. ``report``: numbers
    of the data for metrics.json (a tilt series: ``tilt_axis_angle`` and the tilt-axis check's, ``indreg.alignment.tilt_axis``).
    ``paper``: the paper's simulated phantoms, scored also in the paper's conventions (``ssim_paper``,
    ``psnr_paper``). ``template_known`` False: the run gets no template (a model that reconstructs it, e.g.
    ``spatiotemporal``; ``template_64`` is then only shown). ``targets``: ground truths of the model's outputs by
    name (``frames`` ``(K, *shape)``, ``template``), scored as ``<name>_ssim`` (mean over a leading frame axis).
    ``convention``: the layout of the user's files (``indreg.io.conventions``; the arrays here are in indreg's), in
    which the run writes its images and data back."""
    domain: ImageDomain
    geometry: object
    operator: object
    template_64: torch.Tensor
    data_64: torch.Tensor
    label: str
    target_64: Optional[torch.Tensor] = None
    clean_64: Optional[torch.Tensor] = None
    snr_db: Optional[float] = None
    report: dict = field(default_factory=dict)
    paper: bool = False
    template_known: bool = True
    targets: dict = field(default_factory=dict)
    convention: str = "indreg"

    @classmethod
    def from_inputs(cls, d: RegistrationInputs) -> "Data":
        """The record of measured data loaded by ``indreg.load``."""
        return cls(domain=d.domain, geometry=d.geometry, operator=d.operator, template_64=d.template,
                   data_64=d.data, label=d.label, target_64=d.target, report=d.report(), convention=d.convention)


@dataclass(frozen=True)
class Source:
    """A data source. ``load(cfg) -> Data`` (or a ``RegistrationInputs``); ``options``: the ``data`` group's keys it
    reads, ``(key, type, default)`` (they join the app's schema; a key two sources share must have one type and
    default); ``check(cfg, require)``: its values' checks before the run, ``require(ok, key, expected, value)``
    raising a one-line error naming the key; ``preflight(cfg)``: what else must hold before the run directory is
    made (files exist); ``measured``: the data are measured, not simulated (the paper's presets' absolute weights
    then give way to the relative ones, ``indreg.units``); ``describe(cfg) -> str``: the data in a few words, for
    the run's first line (:func:`describe`; from the config alone, nothing read)."""
    name: str
    load: Callable
    options: tuple = ()
    check: Optional[Callable] = None
    preflight: Optional[Callable] = None
    measured: bool = False
    doc: str = ""
    describe: Optional[Callable] = None


def register_source(source: Source) -> Source:
    """Add ``source`` to the registry under its name (a name already there is replaced)."""
    return add_to_registry(SOURCES, source, Source, "register_source takes an indreg.experiments.sources.Source")


def get(name: str) -> Source:
    """The source of ``data.source=name``: a registered one, else an entry point ``name`` of the group
    ``indreg.sources``, else ``module:attribute`` imported (a :class:`Source`, registered under ``name``, or a
    function ``cfg -> Data``). Raises :class:`ConfigError` (one line) when it is none of these or cannot be
    imported."""
    if name in SOURCES:
        return SOURCES[name]
    try:
        obj, problem = (_import(name) if ":" in name else _entry_point(name)), None
    except Exception as e:   # the user's module: a missing module or attribute, a syntax error, ... as one line
        obj, problem = None, f"{type(e).__name__}: {' '.join(str(e).split())}"
    except SystemExit as e:   # the module called sys.exit() at import
        obj, problem = None, f"it called sys.exit({e.code!r}) at import"
    if problem is not None:   # raised outside the except: no chained context in the one-line message
        raise ConfigError(f"invalid config value data.source={name!r}: cannot import it ({problem})")
    if obj is None:
        known = sorted(SOURCES) + sorted(ep.name for ep in _entry_points())
        raise ConfigError(f"invalid config value data.source={name!r}: expected one of {', '.join(known)} or an "
                          "importable module:function (e.g. my_package.my_module:my_source)")
    if isinstance(obj, Source):
        SOURCES[name] = obj
        return obj
    if not callable(obj):
        raise ConfigError(f"invalid config value data.source={name!r}: {type(obj).__name__} is not callable; "
                          "expected a function cfg -> Data or an indreg.experiments.sources.Source")
    return Source(name, obj)


def resolve(name: str) -> Callable:
    """The load function of ``data.source=name`` (:func:`get`)."""
    return get(name).load


@contextmanager
def calling(source: Source, what: str):
    """Around a plug-in source's ``load`` / ``check`` / ``preflight``: anything it raises but a ``ConfigError`` or
    ``DataFileError`` (the contract's one-line errors) becomes a ``ConfigError`` naming the source, ``what`` and
    the exception, in one line. The built-in sources' errors pass unchanged."""
    try:
        yield
    except (ConfigError, DataFileError):
        raise
    except Exception as e:
        if str(getattr(getattr(source, what), "__module__", "")).startswith("indreg."):   # a built-in function
            raise
        raise ConfigError(f"the data source {source.name!r}: its {what} raised {type(e).__name__}: "
                          f"{' '.join(str(e).split())}") from None   # the message has it all: one line


def _type_name(kind) -> str:
    return kind.__name__ if isinstance(kind, type) else str(kind).replace("typing.", "")


def load(cfg: DictConfig) -> Data:
    """The data of ``cfg.data.source`` (:func:`get`)."""
    from ..inputs import RegistrationInputs

    source = get(cfg.data.source)
    with calling(source, "load"):
        data = source.load(cfg)
    if isinstance(data, RegistrationInputs):
        return Data.from_inputs(data)
    if not isinstance(data, Data):
        raise ConfigError(f"data.source={cfg.data.source} returned a {type(data).__name__}: expected an "
                          "indreg.experiments.sources.Data or what indreg.load returns")
    return data


def check_files(cfg: DictConfig) -> None:
    """The source's ``preflight`` (``data=files``: the files exist), before the app creates its run directory."""
    source = get(cfg.data.source)
    if source.preflight is not None:
        with calling(source, "preflight"):
            source.preflight(cfg)


def describe(cfg: DictConfig) -> str:
    """``data.source`` and, if it has :attr:`Source.describe`, its few words (``phantom j -> v (64^2 cells, ...)``);
    a plug-in's ``describe`` that raises leaves the name alone (the line only informs: its ``load`` reports)."""
    source = get(cfg.data.source)
    if source.describe is None:
        return source.name
    try:
        with calling(source, "describe"):
            return f"{source.name} {source.describe(cfg)}"
    except ConfigError:
        return source.name


def is_measured(name: str) -> bool:
    """Whether ``data.source=name`` brings measured data (``Source.measured``); False for one that cannot be had."""
    try:
        return get(name).measured
    except ConfigError:
        return False


def data_fields() -> list:
    """``(key, type, dataclasses.field(default=...))`` of every registered source's keys, for the app's schema; a
    key two sources declare with different types or defaults is a ``ConfigError`` naming both."""
    seen: dict = {}
    for source in SOURCES.values():
        for key, kind, default in source.options:
            if key in seen and seen[key][:2] != (kind, default):
                k0, d0, other = seen[key]
                raise ConfigError(f"data.{key} is declared twice with different types or defaults: by source "
                                  f"{other!r} ({_type_name(k0)}, default {d0!r}) and by source {source.name!r} "
                                  f"({_type_name(kind)}, default {default!r}); "
                                  "rename the plug-in's key")
            seen.setdefault(key, (kind, default, source.name))
    return [(k, kind, field(default=d)) for k, (kind, d, _) in seen.items()]


def _import(path: str):
    """The object ``module:attribute`` (attribute may be dotted, as in entry points)."""
    module, _, attribute = path.partition(":")
    obj = importlib.import_module(module)
    for part in attribute.split("."):
        obj = getattr(obj, part)
    return obj


def _entry_points() -> tuple:
    from importlib.metadata import entry_points

    return tuple(entry_points(group=ENTRY_POINTS))


def _entry_point(name: str):
    """The loaded entry point ``name`` of the group ``indreg.sources``, or None."""
    for ep in _entry_points():
        if ep.name == name:
            return ep.load()
    return None

