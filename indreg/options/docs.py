"""The option table as numpydoc ``Parameters`` entries: ``indreg.register``'s keywords in its docstring
(``help(indreg.register)``) and in the docs site's API reference (``docs/_hooks/register_options.py``), one
generator for both. Needs no torch; the registries (models, solvers, corrections) must be filled first (importing
``indreg.registration.models``, ``solver_registry`` and ``corrections`` does it).
"""
from __future__ import annotations

import re
import textwrap
import typing

from . import all_options

__all__ = ["PLACEHOLDER", "type_text", "entries", "fill"]

#: The line of a docstring that :func:`fill` replaces by the option entries.
PLACEHOLDER = "{options}"


def type_text(option) -> str:
    """The numpydoc type of ``option``: its schema type (``Optional[float]`` -> ``float or None``), or where that
    is ``Any``, its default's type (``object`` when the default is None).

    Parameters
    ----------
    option : indreg.options.Option
        An entry of the option table.

    Returns
    -------
    str
        E.g. ``"int"``, ``"float or None"``, ``"dict"``.
    """
    def name(t) -> str:
        if t is typing.Any:
            return "object"
        origin = typing.get_origin(t)
        if origin is typing.Union:
            args = typing.get_args(t)
            return " or ".join(dict.fromkeys(name(a) for a in args if a is not type(None))) + \
                (" or None" if type(None) in args else "")
        if origin is not None:
            return getattr(origin, "__name__", str(origin))
        return getattr(t, "__name__", str(t))

    if option.type is typing.Any and option.default is not None:
        return type(option.default).__name__
    return name(option.type)


def entries(indent: int = 4, width: int = 116) -> str:
    """Every option of the table (:func:`indreg.options.all_options`) as a numpydoc ``Parameters`` entry:
    ``name : type, default value`` and, indented below, its help line, its config key and where it applies.

    Parameters
    ----------
    indent : int
        Spaces before each entry's first line (its description: 4 more).
    width : int
        Line width the descriptions are wrapped to.

    Returns
    -------
    str
        The entries, one line per name line and wrapped description lines, without a trailing newline.
    """
    pad, lines = " " * indent, []
    for o in all_options():
        key = "" if o.group == "run" else f" Config key ``{o.config_key}``."
        where = f" Only with {o.where()}." if o.where() else ""
        lines.append(f"{pad}{o.name} : {type_text(o)}, default {o.default!r}")
        lines.append(textwrap.fill(f"{o.doc[:1].upper()}{o.doc[1:]}.{key}{where}", width,
                                   initial_indent=pad + "    ", subsequent_indent=pad + "    "))
    return "\n".join(lines)


def fill(doc: str) -> str:
    """``doc`` with its line :data:`PLACEHOLDER` replaced by :func:`entries`, indented as that line.

    Parameters
    ----------
    doc : str
        A docstring with the placeholder alone on a line (raw or cleaned: the entries take its indentation).

    Returns
    -------
    str
        The docstring with the entries; ``doc`` unchanged if it has no placeholder.
    """
    return re.sub(rf"^([ \t]*){re.escape(PLACEHOLDER)}[ \t]*$", lambda m: entries(len(m.group(1))), doc,
                  count=1, flags=re.M)
