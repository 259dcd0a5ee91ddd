"""The console entry point ``indreg-train-momentum``: the command line is checked first, whatever its flags
(:func:`indreg.experiments.cli.guard`: Hydra's ``--experimental-rerun`` and its prefixes, which unpickle a file,
and Hydra settings that run code exit 2, ``--help`` or not); Hydra's flags that only print text (``--help``,
``-h``, ``--hydra-help``) are then answered without importing torch and the training; every other command line
goes to :func:`indreg.learn.train.main` (which ``python -m indreg.learn.train`` and ``torchrun`` run directly)."""
from __future__ import annotations

import sys

__all__ = ["main"]

from .conf import CONFIG_DIR as _CONFIG, CONFIG_NAME as _CONFIG_NAME
#: Hydra's flags that only print text.
_PRINT_ONLY = ("--help", "-h", "--hydra-help")
PROG = "indreg-train-momentum"                          # = indreg.learn.train.PROG


def main() -> None:
    """``indreg-train-momentum [key=value ...]``."""
    from ..experiments import cli

    argv = sys.argv[1:]
    cli.guard(argv, PROG)   # before Hydra parses anything: it reads the rerun flag before --help
    if any(a in _PRINT_ONLY for a in argv):
        import hydra

        if cli.answers(argv) and cli.print_help(_CONFIG, _CONFIG_NAME, argv):
            return

        hydra.main(version_base="1.3", config_path=str(_CONFIG), config_name=_CONFIG_NAME)(_task)()
    else:
        from .train import main as train_main

        train_main()


def _task(cfg) -> None:
    from .train import _task as train_task

    train_task(cfg)


if __name__ == "__main__":
    main()
