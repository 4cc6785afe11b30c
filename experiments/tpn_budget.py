"""The TPN's stage-2 budget on val (issue 24): does a larger budget make the TPN help?

    python experiments/tpn_budget.py --check     # recompute budget.json and budget.md
    python experiments/tpn_budget.py             # rewrite them from the runs' files

The sweep was made before network parity (issue 39) and is kept, runs included, in
experiments/results/before_parity/tpn_budget (the default --out;
docs/history/why-gains-small.md). It trained, for each base row (Baseline, ORG + IL;
seed 100, 5 M env steps, dropout 0), a TPN of 40 k and one of 400 k stage-2 episodes
(OUT/runs/<base>-s100/tpn-<budget>) and evaluated each on the val split at test-time
learning rates 1e-4, 1e-3 and 1e-2, and the base alone, on the same val episodes; the
test split was never touched. (The script that trained it: `git show
df03751:experiments/tpn_budget.py`; this one only regenerates or checks its page.)

OUT/budget.json holds the summary and OUT/budget.md the table, both recomputed from the
committed run files (config, metrics and val results, each results JSON checked against
its per-episode outcomes) for the sweep budget.json records: per base and budget, the
stage-2 val cross-entropy and accuracy, val success at each lr, the lr chosen on val, and
its gain over the base alone with a 95% t interval paired by val episode (the lr was
chosen on the same episodes, so the interval of the chosen lr is optimistic). The page is
the tables library's (orgnav_jax/tables/before_parity.py: tpn_budget_pages).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orgnav_jax.errors import run_cli
from orgnav_jax.tables import pages
from orgnav_jax.tables.before_parity import tpn_budget_pages

OUT = Path(__file__).resolve().parent / "results" / "before_parity" / "tpn_budget"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=OUT,
                    help="the sweep's folder (budget.json, runs/); default the committed one")
    ap.add_argument("--check", action="store_true",
                    help="recompute OUT's budget.json and budget.md; exit 1 on a difference")
    args = ap.parse_args(argv)
    files = tpn_budget_pages(args.out)       # a missing or bad file: one line, exit 2
    status = pages.regenerate(files, args.check)
    if not args.check:
        print(files[args.out / "budget.md"], end="")
    return status


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
