"""The paper's suite-3 table from a multirun, from the checkout: the same as ``indreg-sweep-table MULTIRUN_DIR``
(``python -m indreg.experiments.sweep``); see ``indreg-sweep-table --help``."""
from indreg.experiments.sweep import main

if __name__ == "__main__":
    main()
