"""The app's user errors, at the bottom of ``indreg.experiments`` (imported by ``config`` and ``sources`` alike).

A bad data file raises ``indreg.io.DataFileError``; a bad config value :class:`ConfigError`. The app ends either
with one line, exit status 1 (``indreg.experiments.register``).
"""


class ConfigError(ValueError):
    """An invalid config value; the message names the key (e.g. ``solver.gamma``)."""
