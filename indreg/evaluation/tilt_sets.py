"""``indreg-score``'s ``--tilts NAME=SPEC``: named sets of a stack's tilts (indices, angle ranges), checked in one
line; torch-free (the command line is checked before torch loads)."""
from __future__ import annotations

__all__ = ["tilt_set", "parse_sets"]


def tilt_set(spec: str, degrees, name: str = "--tilts") -> list:
    """The sorted section indices of ``spec`` (module Convention) among ``len(degrees)`` tilts; a one-line
    ValueError naming ``name`` for a bad term or an empty set."""
    count, chosen = len(degrees), set()
    for item in str(spec).split(","):
        keep = set(range(count))
        for term in item.strip().split("&"):
            keep &= _term(term.strip(), degrees, name, spec)
        chosen |= keep
    if not chosen:
        raise ValueError(f"{name} {spec!r} selects no tilt of the {count}")
    return sorted(chosen)


def _term(t: str, degrees, name: str, spec: str) -> set:
    count = len(degrees)
    try:
        if t in ("all", "odd", "even"):
            return set(range(count)) if t == "all" else set(range(1 if t == "odd" else 0, count, 2))
        if t.startswith(">="):
            return {i for i in range(count) if abs(degrees[i]) >= float(t[2:]) - 1e-9}
        if t.startswith("<"):
            return {i for i in range(count) if abs(degrees[i]) < float(t[1:]) - 1e-9}
        lo, _, hi = t.partition("-")
        a, b = int(lo), int(hi or lo)
    except ValueError:
        raise ValueError(f"{name} {spec!r}: {t!r} is not i, i-j, odd, even, all, >=D or <D") from None
    if not 0 <= a <= b < count:
        raise ValueError(f"{name} {spec!r}: {t!r} is outside the stack's sections 0-{count - 1}")
    return set(range(a, b + 1))


def parse_sets(items: list, degrees) -> dict:
    """``{name: indices}`` of ``--tilts NAME=SPEC`` items (default ``all=all``)."""
    out = {}
    for item in items or ["all=all"]:
        name, eq, spec = item.partition("=")
        if not eq or not name.strip() or name.strip() in out:
            raise ValueError(f"--tilts must be NAME=SPEC with a new NAME, got {item!r}")
        out[name.strip()] = tilt_set(spec, degrees, f"--tilts {name.strip()}")
    return out
