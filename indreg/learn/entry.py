"""The console entry point ``indreg-train-momentum``: Hydra's flags that only print text (``--help``,
``--hydra-help``) are answered without importing torch and the training; every other command line goes to
:func:`indreg.learn.train.main` (which ``python -m indreg.learn.train`` and ``torchrun`` run directly)."""
from __future__ import annotations

import sys

__all__ = ["main"]

from .conf import CONFIG_DIR as _CONFIG, CONFIG_NAME as _CONFIG_NAME
#: Hydra's flags that only print text; ``--experimental-rerun`` (it unpickles a file) is left to train.main.
_PRINT_ONLY = ("--help", "-h", "--hydra-help")


def main() -> None:
    """``indreg-train-momentum [key=value ...]``."""
    argv = sys.argv[1:]
    if any(a in _PRINT_ONLY for a in argv) and not any(a.startswith("--experimental-rerun") for a in argv):
        import hydra

        from ..experiments import cli

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
