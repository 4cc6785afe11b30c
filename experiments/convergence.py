"""When rows stop learning: the convergence rule (orgnav_jax/tables/convergence.py) on
runs' val curves, and the budget campaign's page.

    python experiments/convergence.py check RUN_DIR...     # the rule per row (RUN-s<seed>)
    python experiments/convergence.py report               # writes the campaign's page
    python experiments/convergence.py report --check       # recompute it; exit 1 on a difference

`check` groups run directories into rows by their name without -s<seed> and prints, per
row, the rule at its last shared evaluation and the first evaluation where it held (the
row's budget B). `report` writes experiments/results/convergence/report.md from the
committed files of the campaign's runs (experiments/results/convergence/runs/) and of the
5 M calibrated table (its rows' val curves by tenth of the budget), and the learning-curve
figure docs/figures/convergence.png (not compared by --check).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orgnav_jax.errors import run_cli
from orgnav_jax.plots.curves import plot_curves
from orgnav_jax.tables.convergence_page import campaign_rows, report, rows_of, verdict_lines
from orgnav_jax.tables.pages import regenerate

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "convergence"
FIGURE = ROOT / "docs" / "figures" / "convergence.png"
TABLE_5M = ROOT / "experiments" / "results" / "table_calibrated"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/convergence.py",
                                 description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    chk = sub.add_parser("check", help="the rule on rows of run directories")
    chk.add_argument("run_dirs", nargs="+")
    rep = sub.add_parser("report", help="write (or --check) the campaign's page")
    rep.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    if args.command == "check":
        for line in verdict_lines(rows_of(args.run_dirs)):
            print(line)
        return 0
    status = regenerate({OUT / "report.md": report(OUT, TABLE_5M, ROOT)}, args.check)
    rows = campaign_rows(OUT)
    if not args.check and rows:
        plot_curves(rows, FIGURE, metrics=("success",), quiet=True)
        print(f"wrote {OUT / 'report.md'} and {FIGURE}")
    return status


if __name__ == "__main__":
    sys.exit(run_cli(main))
