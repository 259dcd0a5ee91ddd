"""The paper's suite-3 table from a multirun: ``python scripts/sweep_table.py MULTIRUN_DIR [--convention range]``.

Writes ``table.md`` (sigma rows x gamma columns, ``SSIM / PSNR`` with the paper's value in parentheses) and
``table.csv`` (one row per run) into MULTIRUN_DIR (or ``--out``) and prints the Markdown table.
"""
from indreg.experiments.sweep import main

if __name__ == "__main__":
    main()
