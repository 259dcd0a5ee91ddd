"""Collect a multirun's ``metrics.json`` files into the paper's suite-3 table (sigma rows x gamma columns).

Each cell is ``SSIM / PSNR`` of one run, next to the paper's published value (table
Test_suite_3:Sensitivity_table). The paper's numbers are in its SSIM/PSNR convention (data range 2 / 1 or 2,
``ssim_paper`` / ``psnr_paper``), so that convention is the default; ``convention="range"`` uses the data range
of the target (``ssim`` / ``psnr``).
"""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path

from .._outfiles import open_replacing


#: The grid of the paper's suite-3 table (conf/sweep/suite3_table.yaml sweeps the same values).
SUITE3_GAMMAS = (1e-7, 1e-5, 1e-3, 1e-1, 10.0)
SUITE3_SIGMAS = (1.0, 2.0, 2.5, 3.0, 4.0, 8.0)

#: The paper's table: PAPER[sigma][gamma] = (SSIM, PSNR in dB).
PAPER = {
    1.0: dict(zip(SUITE3_GAMMAS, [(0.8958, 26.69), (0.8958, 26.69), (0.8957, 26.69), (0.8820, 26.18), (0.6800, 17.82)])),
    2.0: dict(zip(SUITE3_GAMMAS, [(0.9039, 26.96), (0.9039, 26.96), (0.9038, 26.96), (0.8958, 26.72), (0.6967, 18.45)])),
    2.5: dict(zip(SUITE3_GAMMAS, [(0.9018, 26.90), (0.9018, 26.90), (0.9017, 26.89), (0.8964, 26.74), (0.7057, 18.71)])),
    3.0: dict(zip(SUITE3_GAMMAS, [(0.9007, 26.90), (0.9007, 26.90), (0.9006, 26.89), (0.8968, 26.77), (0.7164, 19.03)])),
    4.0: dict(zip(SUITE3_GAMMAS, [(0.8992, 26.88), (0.8992, 26.88), (0.8992, 26.87), (0.8979, 26.77), (0.7426, 19.79)])),
    8.0: dict(zip(SUITE3_GAMMAS, [(0.8305, 24.15), (0.8305, 24.15), (0.8307, 24.16), (0.8438, 24.84), (0.7960, 21.27)])),
}
CONVENTIONS = {"paper": ("ssim_paper", "psnr_paper"), "range": ("ssim", "psnr")}


def collect(multirun_dir) -> list:
    """One record per ``metrics.json`` below ``multirun_dir``: gamma, sigma, figures of merit, run dir."""
    records = []
    for path in sorted(Path(multirun_dir).rglob("metrics.json")):
        try:
            with open(path) as f:
                m = json.load(f)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path} is not JSON ({e})") from None
        try:
            hp = m["hparams"]
            records.append({"gamma": float(hp["gamma"]), "sigma": float(hp["sigma"]), "run": str(path.parent),
                            "iterations": m.get("iterations"),
                            **{k: float(m[k]) for k in ("ssim", "psnr", "ssim_paper", "psnr_paper")}})
        except (KeyError, TypeError) as e:
            raise ValueError(f"{path} is not the metrics.json of a finished indreg-register run with a target "
                             f"(status {m.get('status') if isinstance(m, dict) else None!r}, missing {e})") from None
    if not records:
        raise FileNotFoundError(f"no metrics.json below {multirun_dir} (a multirun dir of indreg-register)")
    return records


def _key(x: float) -> float:
    return float(f"{x:.6g}")


def grid(records: list) -> tuple:
    """Sorted sigmas, gammas (the paper's and the runs') and ``{(sigma, gamma): record}``."""
    cells = {(_key(r["sigma"]), _key(r["gamma"])): r for r in records}
    sigmas = sorted({s for s, _ in cells})
    gammas = sorted({g for _, g in cells})
    return sigmas, gammas, cells


def _paper(sigma: float, gamma: float):
    return PAPER.get(sigma, {}).get(gamma)


def markdown(records: list, convention: str = "paper") -> str:
    """The table in Markdown: each cell ``ours SSIM / PSNR (paper SSIM / PSNR)``."""
    ks, kp = CONVENTIONS[convention]
    sigmas, gammas, cells = grid(records)
    head = "| sigma \\ gamma | " + " | ".join(f"{g:g}" for g in gammas) + " |"
    lines = [f"SSIM / PSNR (dB), {convention} convention; in parentheses the paper's table", "",
             head, "|---" * (len(gammas) + 1) + "|"]
    for s in sigmas:
        row = []
        for g in gammas:
            r = cells.get((s, g))
            ours = f"{r[ks]:.4f} / {r[kp]:.2f}" if r else "—"
            p = _paper(s, g)
            row.append(ours + (f" ({p[0]:.4f} / {p[1]:.2f})" if p else ""))
        lines.append(f"| {s:g} | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def csv_text(records: list) -> str:
    """Long format: one row per run with both conventions and the paper's values."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["sigma", "gamma", "ssim_paper", "psnr_paper", "ssim", "psnr", "paper_ssim", "paper_psnr",
                "iterations", "run"])
    sigmas, gammas, cells = grid(records)
    for s in sigmas:
        for g in gammas:
            r = cells.get((s, g))
            if r is None:
                continue
            p = _paper(s, g) or ("", "")
            w.writerow([s, g, r["ssim_paper"], r["psnr_paper"], r["ssim"], r["psnr"], p[0], p[1],
                        r["iterations"], r["run"]])
    return buf.getvalue()


PROG = "indreg-sweep-table"


def main(argv=None) -> None:
    """Console entry point ``indreg-sweep-table MULTIRUN_DIR`` (also ``python -m indreg.experiments.sweep``):
    writes ``table.md`` and ``table.csv`` and prints the table. Without arguments: a usage error (exit 2); a
    directory without runs: one line ``indreg-sweep-table: error: ...`` (exit 1)."""
    import argparse

    from .cli import exit_error

    ap = argparse.ArgumentParser(prog=PROG, description="The paper's suite-3 table (sigma rows x gamma columns, "
                                 "SSIM / PSNR) from a multirun directory of indreg-register, next to the "
                                 "paper's numbers; writes table.md and table.csv.")
    ap.add_argument("multirun_dir", help="hydra.sweep.dir of the multirun (e.g. multirun/suite3_table)")
    ap.add_argument("--convention", choices=sorted(CONVENTIONS), default="paper",
                    help="paper: the paper's SSIM/PSNR convention (default); range: data range of the target")
    ap.add_argument("--out", default=None, help="write table.md and table.csv here (default: the multirun dir)")
    args = ap.parse_args(argv)
    try:
        records = collect(args.multirun_dir)
        md = markdown(records, args.convention)
        out = Path(args.out or args.multirun_dir)
        out.mkdir(parents=True, exist_ok=True)
        for name, text in (("table.md", md), ("table.csv", csv_text(records))):
            with open_replacing(out / name, "w") as f:   # a fresh file renamed over it: no link followed
                f.write(text)
    except (OSError, ValueError) as e:  # no runs, an unreadable or foreign metrics.json, an unwritable --out
        exit_error(PROG, str(e))
    print(md)
    print(f"wrote {out / 'table.md'} and {out / 'table.csv'} ({len(records)} runs)")


if __name__ == "__main__":
    main()
