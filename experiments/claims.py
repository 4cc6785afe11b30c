"""The paper's claims, checked on a table's runs: paired differences over seeds, with
intervals, a one-sided paired test and a three-level verdict.

    python experiments/claims.py experiments/results/table_5m            # writes the files
    python experiments/claims.py --check experiments/results/table_5m    # recompute all
    python experiments/claims.py --check experiments/results/before_parity/table_5m
                                             # the table made before network parity

TABLE is a run_table.py output directory (spec.json, runs/, results.json, table.md). The
results are read from the runs' own files (OUT/runs/<row>-s<seed>/test_results.json,
.../tpn/test_<variant>.json): every summary is recomputed from the per-episode outcomes
kept in them and must equal the summary stored beside them. For every claim (row vs
reference row, a sign) and each metric (success, SPL), over the seeds both rows have:

- the paired difference per seed (percentage points), its mean, the sample std (ddof 1);
- a 95% t interval of the mean and a one-sided paired t-test (H1: the claimed sign);
- a 95% bootstrap interval that resamples seeds and, within each seed, test episodes
  (the rows share the seeded episode set, so episodes pair too; 2,000 resamples, fixed
  generator seed);
- the verdict: "holds in every seed", "holds on average (k of n seeds)" or "does not
  hold"; and whether the t interval excludes 0.

provenance.md is the table of which code and which machine made each run, generated from
the runs' provenance.json records. The claims, the statistics and the files are the
tables library's (orgnav_jax/tables: claims.py, stats.py, table_files.py).

--check recomputes results.json, table.md and claims.md (and provenance.md, where the
table has one; convergence.md, where its spec has "converged": true) from the runs' files
and exits 1 on any difference (CI runs it on the committed tables).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orgnav_jax.errors import run_cli
from orgnav_jax.tables import claims, table_files
from orgnav_jax.tables.rows import lr_tag
from orgnav_jax.tables.runs import read_table_dir
from orgnav_jax.tables.spec import read_table_spec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("table", help="a run_table.py output directory (with spec.json)")
    ap.add_argument("--per-category", nargs=2, metavar=("ROW", "REF"), default=None,
                    help="print ROW vs REF success per target category and group "
                         "(anchored small objects, anchors, others), e.g. org baseline")
    ap.add_argument("--compact", action="store_true",
                    help="print the README's short claims table (measured claims only)")
    ap.add_argument("--before", metavar="TABLE", default=None,
                    help="print each claim measured in both tables as before (TABLE) -> "
                         "after (this table), e.g. experiments/results/before_parity/table_5m")
    ap.add_argument("--check", action="store_true",
                    help="recompute results.json, table.md, claims.md (and provenance.md "
                         "where present) from the runs' files; exit 1 on any difference, "
                         "write nothing")
    args = ap.parse_args(argv)
    out = Path(args.table)
    read_table_spec(out)                  # a missing or bad table: one line, nothing written
    if args.per_category:
        print(claims.per_category(out, *args.per_category))
        return 0
    if args.compact:
        spec, results, episodes = read_table_dir(out)
        print(claims.compact(results, episodes, lr_tag(spec["rows"]), spec))
        return 0
    if args.before:
        print(claims.before_after(out, Path(args.before)), end="")
        return 0
    if args.check:
        return table_files.check_or_write(out, check_only=True)
    print(table_files.write_all(out)["claims.md"])
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
