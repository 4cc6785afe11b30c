"""Issue 24, 4x the budget: the 5 M table's Baseline, ORG and ORG + IL runs extended to
20 M env steps (seeds 0-2) and their TPNs re-trained, against the same seeds at 5 M.

    python experiments/run_table.py --spec experiments/tables/table_20m.json
    python experiments/budget_20m.py            # writes table_20m/budget.md
    python experiments/budget_20m.py --check    # recompute it; exit 1 on a difference

Both tables (SHORT, LONG) were made before network parity (issue 39) and are kept in
experiments/results/before_parity/ (docs/history/why-gains-small.md).

budget.md has four tables, all from the runs' files (tables/runs.read_table_dir: every
results JSON checked against its per-episode outcomes; metrics.jsonl for the curves),
made by orgnav_jax/tables/before_parity.py (budget_20m_markdown):
- test success per row at 5 M and 20 M, the paired change 20 M - 5 M per seed with its
  95% t interval and verdict (tables/stats.py; "20 M > 5 M");
- every claim the two tables share, on the same seeds, at 5 M and at 20 M, and whether
  its verdict changed;
- the val curves: mean val success over the seeds at the first val record at or after 5,
  10, 15 and 20 M, and the change from 15 M to 20 M per seed with its interval (a curve
  has flattened when that change is small and its interval includes 0);
- the learned adjacency's anchor statistic (knob.py) of the ORG and ORG + IL runs at 5 M
  (the table's runs retrained bit for bit: rerun_org_5m, rerun_org_il_5m) and at 20 M
  (`python experiments/knob.py --adjacency experiments/results/before_parity/table_20m/runs/org*-s*`
  writes each run's adjacency.json from its best-on-val checkpoint).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orgnav_jax.errors import run_cli
from orgnav_jax.tables import pages
from orgnav_jax.tables.before_parity import LONG, budget_20m_markdown

# Both tables were made before network parity (issue 39) and are kept in
# results/before_parity (docs/history/why-gains-small.md).
RESULTS = Path(__file__).resolve().parent / "results" / "before_parity"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="recompute budget.md from the runs' files; exit 1 on a difference")
    args = ap.parse_args(argv)
    text = budget_20m_markdown(RESULTS)    # a missing or bad file: run_cli's one line, exit 2
    status = pages.regenerate({RESULTS / LONG / "budget.md": text}, args.check)
    if not args.check:
        print(text)
    return status


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
