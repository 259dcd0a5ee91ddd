"""The app's user errors, at the bottom of ``indreg.experiments`` (imported by ``config`` and ``sources`` alike).

A bad data file raises ``indreg.io.DataFileError``; a bad config value :class:`ConfigError`. The app ends either
with one line, exit status 1 (``indreg.experiments.register``). A misspelt key is answered with the valid key
nearest to it (:func:`nearest_key`).
"""
from __future__ import annotations

import difflib


class ConfigError(ValueError):
    """An invalid config value; the message names the key (e.g. ``solver.gamma``)."""


def dotted_keys(node, prefix: str = "") -> list:
    """Every dotted key of a (nested) mapping; values are not read (nothing is resolved).

    Parameters
    ----------
    node : mapping
        E.g. an OmegaConf ``DictConfig``.
    prefix : str
        Put before every key.

    Returns
    -------
    list of str
        ``["data", "data.template", ...]``: the mappings' own keys too.
    """
    out = []
    for key in node.keys():
        out.append(f"{prefix}{key}")
        try:
            child = node._get_node(key) if hasattr(node, "_get_node") else node[key]
        except Exception:   # noqa: BLE001 (a value that cannot be read is a leaf here)
            continue
        if hasattr(child, "keys") and not _is_none(child):
            out += dotted_keys(child, f"{prefix}{key}.")
    return out


def _is_none(node) -> bool:
    return bool(getattr(node, "_is_none", lambda: False)())


def nearest_key(key: str, known) -> str | None:
    """The valid key nearest to a misspelt one (``difflib``'s ratio 0.6): under a parent that exists, among its
    keys (``data.templat`` -> ``data.template``); else as a whole (``sover.gamma`` -> ``solver.gamma``) or by its
    last part (``templat`` -> ``data.template``).

    Parameters
    ----------
    key : str
        The misspelt dotted key.
    known : iterable of str
        The valid dotted keys (:func:`dotted_keys`).

    Returns
    -------
    str or None
        The nearest valid key, None if none is close.
    """
    known = list(dict.fromkeys(known))
    parent, _, last = key.rpartition(".")
    if parent in known:
        match = difflib.get_close_matches(last, [k.rpartition(".")[2] for k in known
                                                 if k.rpartition(".")[0] == parent], n=1)
        return f"{parent}.{match[0]}" if match else None
    match = difflib.get_close_matches(key, known, n=1)
    if match:
        return match[0]
    by_last = {}
    for k in known:
        by_last.setdefault(k.rpartition(".")[2], k)
    match = difflib.get_close_matches(last, list(by_last), n=1)
    return by_last[match[0]] if match else None


def did_you_mean(key: str, known) -> str:
    """The hint for a misspelt key.

    Parameters
    ----------
    key : str
        The misspelt dotted key.
    known : iterable of str
        The valid dotted keys.

    Returns
    -------
    str
        ``"did you mean data.template?"`` (:func:`nearest_key`), ``""`` when none is close.
    """
    near = nearest_key(key, known)
    return f"did you mean {near}?" if near and near != key else ""
