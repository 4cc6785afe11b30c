"""Issue 24, 4x the budget: the 5 M table's Baseline, ORG and ORG + IL runs extended to
20 M env steps (seeds 0-2) and their TPNs re-trained, against the same seeds at 5 M.

    python experiments/run_table.py --spec experiments/tables/table_20m.json
    python experiments/budget_20m.py            # writes table_20m/budget.md
    python experiments/budget_20m.py --check    # recompute it; exit 1 on a difference

Both tables (SHORT, LONG) were made before network parity (issue 39) and are kept in
experiments/results/before_parity/ (docs/history/why-gains-small.md).

budget.md has three tables, all from the runs' files (claims.read_table_dir: every
results JSON checked against its per-episode outcomes; metrics.jsonl for the curves):
- test success per row at 5 M and 20 M, the paired change 20 M - 5 M per seed with its
  95% t interval and verdict (claims.statistics; "20 M > 5 M");
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

import numpy as np

from orgnav_jax.training.run_dir import METRICS_FILE, read_metrics

sys.path.insert(0, str(Path(__file__).resolve().parent))
import claims  # noqa: E402  (sibling script: the paired statistics, reading a table dir)
import knob  # noqa: E402  (sibling script: the adjacency reports)
from orgnav_jax.errors import run_cli  # noqa: E402

# Both tables were made before network parity (issue 39) and are kept in
# results/before_parity (docs/history/why-gains-small.md).
RESULTS = Path(__file__).resolve().parent / "results" / "before_parity"
SHORT, LONG = RESULTS / "table_5m", RESULTS / "table_20m"
MILESTONES = (5_000_000, 10_000_000, 15_000_000, 20_000_000)
NAV_ROWS = ("baseline", "org", "org_il")


def restrict(results: dict, seeds: list[str]) -> dict:
    """results[row][seed] kept for `seeds` only."""
    return {row: {s: v for s, v in r.items() if s in seeds} for row, r in results.items()}


def row_changes(short: dict, long: dict) -> list[str]:
    lines = ["| row | seeds | 5 M | 20 M | 20 M - 5 M per seed | mean [95% t interval] | "
             "verdict (20 M > 5 M) |", "|---|---|---|---|---|---|---|"]
    for row in long:
        d, seeds = claims.paired({"a": long[row], "b": short.get(row, {})}, "a", "b")
        if not seeds:
            continue
        st = claims.statistics(d, 1)
        mean = lambda r: np.mean([100 * r[s]["success"] for s in seeds])
        lines.append(f"| {row} | {','.join(seeds)} | {mean(short[row]):.1f} | "
                     f"{mean(long[row]):.1f} | {', '.join(f'{x:+.1f}' for x in d)} | "
                     f"{st['mean']:+.1f} {claims.interval_text(st['interval'])} | "
                     f"{st['verdict']} |")
    return lines


def claim_changes(short: dict, long: dict, lr: str) -> list[str]:
    lines = ["| claim | seeds | 5 M: mean [95% t interval] | 5 M verdict | 20 M: mean "
             "[95% t interval] | 20 M verdict | changed |", "|---|---|---|---|---|---|---|"]
    headline = [("full model > Baseline (the paper's headline, +12.9)", f"org_il+tpn@{lr}",
                 "baseline", 1)]
    for name, row, ref, sign in claims.claims(lr) + headline:
        d_long, seeds = claims.paired(long, row, ref)
        d_short, seeds_short = claims.paired(short, row, ref)
        if not seeds or seeds_short != seeds:
            continue
        a, b = claims.statistics(d_short, sign), claims.statistics(d_long, sign)
        lines.append(f"| {name} | {','.join(seeds)} | {a['mean']:+.1f} "
                     f"{claims.interval_text(a['interval'])} | {a['verdict']} | "
                     f"{b['mean']:+.1f} {claims.interval_text(b['interval'])} | "
                     f"{b['verdict']} | {'no' if a['verdict'] == b['verdict'] else 'yes'} |")
    return lines


def val_at(run_dir: Path, steps: int) -> float:
    """Val success (points) of the first val record at or after `steps` env steps (a run
    stops at the end of the chunk that crosses its budget, so its last record is there)."""
    vals = [r for r in read_metrics(run_dir) if r["kind"] == "val" and r["env_steps"] >= steps]
    if not vals:
        raise ValueError(f"{run_dir / METRICS_FILE}: no val record at or after {steps:,} "
                         "env steps")
    return 100 * float(vals[0]["success"])


def curve_lines(out: Path, seeds: list[str]) -> list[str]:
    head = " | ".join(f"val at {m // 1_000_000} M" for m in MILESTONES)
    lines = [f"| row | seeds | {head} | 20 M - 15 M per seed | mean [95% t interval] |",
             "|---|---|" + "---|" * len(MILESTONES) + "---|---|"]
    for row in NAV_ROWS:
        runs = [out / "runs" / f"{row}-s{s}" for s in seeds]
        v = np.array([[val_at(r, m) for m in MILESTONES] for r in runs])   # (seeds, M)
        d = v[:, -1] - v[:, -2]
        st = claims.statistics(d, 1)
        lines.append(f"| {row} | {','.join(seeds)} | "
                     + " | ".join(f"{x:.1f}" for x in v.mean(0))
                     + f" | {', '.join(f'{x:+.1f}' for x in d)} | {st['mean']:+.1f} "
                     f"{claims.interval_text(st['interval'])} |")
    return lines


def adjacency_section(long_dir: Path, seeds: list[str]) -> list[str]:
    lines = ["| row | budget | seed | anchor AUC | anchor pairs above the mean | p-value |",
             "|---|---|---|---|---|---|"]
    for row in ("org", "org_il"):
        for budget, where in (("5 M", RESULTS / f"rerun_{row}_5m"), ("20 M", long_dir)):
            lines += knob.adjacency_lines(f"| {row} | {budget} |",
                                          knob.adjacency_reports(where, row, seeds))
    return lines


def markdown(short_dir: Path = SHORT, long_dir: Path = LONG) -> str:
    spec, long, _ = claims.read_table_dir(long_dir)
    seeds = [str(s) for s in spec["seeds"]]
    _, short, _ = claims.read_table_dir(short_dir)
    short = restrict(short, seeds)
    rows = [r for r in spec["rows"] if all(s in long.get(r, {}) for s in seeds)]
    long = {r: long[r] for r in rows}
    return "\n".join(
        [f"# 5 M against 20 M env steps (seeds {','.join(seeds)}; test success, points)",
         "", "Written by `python experiments/budget_20m.py` from "
         f"`{short_dir.name}` and `{long_dir.name}`.", "", "## Each row", ""]
        + row_changes(short, long)
        + ["", "## The claims on the same seeds", ""]
        + claim_changes(short, long, claims.lr_tag(spec))
        + ["", "## The val curves (success, points)", ""]
        + curve_lines(long_dir, seeds)
        + ["", "## The learned adjacency (anchor pairs against other same-room-type pairs; "
           "AUC 0.5 = chance)", ""]
        + adjacency_section(long_dir, seeds)) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="recompute budget.md from the runs' files; exit 1 on a difference")
    args = ap.parse_args(argv)
    text = markdown()          # a missing or bad file: run_cli's one line, exit 2
    path = LONG / "budget.md"
    if args.check:
        if not path.exists() or path.read_text() != text:
            print(f"{path}: differs from what the runs' files give", file=sys.stderr)
            return 1
        print(f"{path}: agrees with the runs' files")
        return 0
    path.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
