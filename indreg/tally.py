"""The warnings of a run, counted by kind: those of its set-up (the loader's checks, the orientation probe, an
alignment's angle the data do not determine, ...), of its iterations (``info["warning"]`` in the history) and of its
end (a poor fit).

Notes
-----
- While :func:`tally_warnings` is active, every record of level WARNING or above of the ``indreg`` loggers is
  counted by its kind (:func:`kind_of`), except the loop's own lines about an iteration's warning (marked
  ``extra={"indreg_counted": True}``): those are counted from the history, one per iteration and clause.
- ``warnings`` (``result.warnings``, ``metrics.json``) = iterations that reported a warning + the other
  warnings; ``warnings_by_kind`` = each kind's count (an iteration's clauses counted each).
"""
from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["WarningTally", "tally_warnings", "current", "kind_of", "warning_kinds", "summary", "COUNTED",
           "has_output_handlers"]

#: ``extra`` of a log record that is counted elsewhere (the loop's lines about an iteration's warning).
COUNTED = {"indreg_counted": True}
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|\b(?:nan|inf)\b", re.IGNORECASE)
_STACK: list = []


class WarningTally(logging.Handler):
    """A logging handler counting the WARNING records it sees by kind (:func:`kind_of`); ``kinds`` a Counter."""

    def __init__(self):
        super().__init__(logging.WARNING)
        self.kinds: Counter = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        if not getattr(record, "indreg_counted", False):
            self.kinds[kind_of(record.getMessage())] += 1
        if not _other_handlers(record.name):   # what logging does without a handler: the warning on stderr
            last = logging.lastResort
            if last is not None and record.levelno >= last.level:
                last.handle(record)


def _other_handlers(name: str) -> bool:
    """Whether a record of logger ``name`` reaches a handler other than a tally (else logging's last resort would
    have printed it, and still does)."""
    logger = logging.getLogger(name)
    while logger is not None:
        if any(not isinstance(h, WarningTally) for h in logger.handlers):
            return True
        logger = logger.parent if logger.propagate else None
    return False


@contextmanager
def tally_warnings(logger: str = "indreg") -> Iterator[WarningTally]:
    """Count the warnings of ``logger`` and its children while the block runs (innermost tally: :func:`current`)."""
    tally = WarningTally()
    target = logging.getLogger(logger)
    target.addHandler(tally)
    _STACK.append(tally)
    try:
        yield tally
    finally:
        _STACK.remove(tally)
        target.removeHandler(tally)


def current() -> WarningTally | None:
    """The innermost active :class:`WarningTally`, or ``None``."""
    return _STACK[-1] if _STACK else None


def kind_of(message: str) -> str:
    """A warning's kind: its first clause (up to ``:``, `` (`` or ``;``), numbers as ``#``, at most 80 characters."""
    text = _NUMBER.sub("#", " ".join(str(message).split()))
    head = re.split(r":\s| \(|;", text, maxsplit=1)[0].strip(" .,")
    return head[:80] or "warning"


def warning_kinds(history, tally: WarningTally | None) -> tuple:
    """``(count, by_kind)``: iterations that reported a warning plus the tally's warnings, and every kind's count
    (the iterations' clauses each, the tally's records)."""
    kinds = Counter()
    iterations = 0
    for h in history:
        if h.get("warning"):
            iterations += 1
            kinds.update(kind_of(c) for c in str(h["warning"]).split("; "))
    other = sum(tally.kinds.values()) if tally is not None else 0
    if tally is not None:
        kinds.update(tally.kinds)
    return iterations + other, dict(kinds.most_common())


def summary(count: int, by_kind: dict, shown: int = 3) -> str:
    """``"4 warnings (3 objective increased from # to #, 1 tilt-axis angle not determined by the data)"``."""
    word = "warning" if count == 1 else "warnings"
    if not by_kind:
        return f"{count} {word}"
    parts = [f"{n} {k}" for k, n in list(by_kind.items())[:shown]]
    more = f", {len(by_kind) - shown} more kinds" if len(by_kind) > shown else ""
    return f"{count} {word} ({', '.join(parts)}{more})"


def has_output_handlers(logger: logging.Logger) -> bool:
    """``logger.hasHandlers()`` not counting tallies."""
    return _other_handlers(logger.name)
