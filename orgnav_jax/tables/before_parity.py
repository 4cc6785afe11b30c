"""The pages of the investigations made before network parity (issue 24; superseded,
docs/history/why-gains-small.md), kept so that their committed pages still regenerate
and `--check` from the committed runs (experiments/knob.py, budget_20m.py,
tpn_budget.py):

- knob.md: ORG's gain over the Baseline against the anchor probability P (knob_*);
- budget.md: the 5 M table's Baseline, ORG and ORG + IL runs against the same seeds at
  20 M env steps (budget_20m_*);
- the TPN's stage-2 budget on val: budget.json and budget.md (tpn_budget_*).

`results` is the folder that holds them all (experiments/results/before_parity).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from orgnav_jax.errors import read_json, read_object
from orgnav_jax.tables import stats
from orgnav_jax.tables.adjacency import adjacency_lines, adjacency_reports
from orgnav_jax.tables.claims import claims
from orgnav_jax.tables.rows import lr_tag
from orgnav_jax.tables.runs import last_val, read_results, read_table_dir, val_at

# ---- the co-occurrence knob (knob.md) -------------------------------------------------

# (P, the table directory of its Baseline and ORG runs, the directory whose ORG runs
# carry the adjacency.json of that P; both under `results`, named so in knob.md)
POINTS = ((0.0, "knob_p0", "knob_p0"), (0.85, "table_5m", "rerun_org_5m"),
          (1.0, "knob_p1", "knob_p1"))
SEEDS = ("0", "1", "2")            # the knob's seeds; at 0.85 the table's seeds 0-2
# The 5 M table's rows with a learned adjacency, each retrained (bit for bit) to recover
# its checkpoints: (row, the directory whose runs carry adjacency.json), seeds 0-4.
TABLE_ADJACENCY = (("org", "rerun_org_5m"), ("org_il", "rerun_org_il_5m"))
TABLE_SEEDS = ("0", "1", "2", "3", "4")


def knob_points(results: Path) -> list[dict]:
    """Per P: success of both rows, the paired ORG - Baseline statistics, adjacency."""
    rows = []
    for p, table, adj_dir in POINTS:
        entry = {"p": p, "table": table, "adj_dir": adj_dir, "seeds": [], "stats": None}
        if (results / table / "spec.json").exists():
            _, res, _ = read_table_dir(results / table)
            seeds = [s for s in SEEDS if s in res.get("org", {}) and
                     s in res.get("baseline", {})]
            if seeds:
                entry["seeds"] = seeds
                entry["baseline"] = [100 * res["baseline"][s]["success"] for s in seeds]
                entry["org"] = [100 * res["org"][s]["success"] for s in seeds]
                d = np.array(entry["org"]) - np.array(entry["baseline"])
                entry["stats"] = stats.statistics(d, 1)
        entry["adjacency"] = adjacency_reports(results / adj_dir, "org", SEEDS)
        rows.append(entry)
    return rows


def knob_table_adjacency(results: Path) -> dict[str, dict[str, dict]]:
    """{row: {seed: report}} of the 5 M table's ORG and ORG + IL runs (TABLE_ADJACENCY)."""
    return {row: adjacency_reports(results / adj_dir, row, TABLE_SEEDS)
            for row, adj_dir in TABLE_ADJACENCY}


def knob_markdown(rows: list[dict], table_runs: dict[str, dict[str, dict]]) -> str:
    """knob.md of knob_points and knob_table_adjacency."""
    lines = ["ORG - Baseline, test success (points), paired by seed:", "",
             "| P (anchor probability) | runs | seeds | Baseline | ORG | "
             "ORG - Baseline per seed | mean [95% t interval] | verdict |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        st = r["stats"]
        if st is None:
            lines.append(f"| {r['p']:g} | {r['table']} | - | | | | not measured yet | |")
            continue
        lines.append(
            f"| {r['p']:g} | {r['table']} | {','.join(r['seeds'])} | "
            f"{np.mean(r['baseline']):.1f} | {np.mean(r['org']):.1f} | "
            f"{', '.join(f'{x:+.1f}' for x in st['differences'])} | {st['mean']:+.1f} "
            f"{stats.interval_text(st['interval'])} | {st['verdict']} |")
    lines += ["", "The learned adjacency of the ORG runs (best-on-val checkpoint): AUC of the "
              "anchor pairs against the other same-room-type pairs (0.5 = chance) and the "
              "anchor pairs' p-value (plots.adjacency.anchor_pair_report):", "",
              "| P | runs | seed | anchor AUC | anchor pairs above the mean | p-value |",
              "|---|---|---|---|---|---|"]
    for r in rows:
        lines += adjacency_lines(f"| {r['p']:g} | {r['adj_dir']} |", r["adjacency"])
    lines += ["", "The 5 M table's ORG and ORG + IL runs (P = 0.85, seeds 0-4, each row "
              "retrained bit for bit to recover its checkpoints):", "",
              "| row | runs | seed | anchor AUC | anchor pairs above the mean | p-value |",
              "|---|---|---|---|---|---|"]
    for row, adj_dir in TABLE_ADJACENCY:
        lines += adjacency_lines(f"| {row} | {adj_dir} |", table_runs[row])
    return "\n".join(lines) + "\n"


# ---- 5 M against 20 M env steps (table_20m/budget.md) ----------------------------------

SHORT, LONG = "table_5m", "table_20m"          # the two tables, under `results`
MILESTONES = (5_000_000, 10_000_000, 15_000_000, 20_000_000)
NAV_ROWS = ("baseline", "org", "org_il")


def _restrict(results: dict, seeds: list[str]) -> dict:
    """results[row][seed] kept for `seeds` only."""
    return {row: {s: v for s, v in r.items() if s in seeds} for row, r in results.items()}


def _row_changes(short: dict, long: dict) -> list[str]:
    lines = ["| row | seeds | 5 M | 20 M | 20 M - 5 M per seed | mean [95% t interval] | "
             "verdict (20 M > 5 M) |", "|---|---|---|---|---|---|---|"]
    for row in long:
        d, seeds = stats.paired({"a": long[row], "b": short.get(row, {})}, "a", "b")
        if not seeds:
            continue
        st = stats.statistics(d, 1)
        mean = lambda r: np.mean([100 * r[s]["success"] for s in seeds])
        lines.append(f"| {row} | {','.join(seeds)} | {mean(short[row]):.1f} | "
                     f"{mean(long[row]):.1f} | {', '.join(f'{x:+.1f}' for x in d)} | "
                     f"{st['mean']:+.1f} {stats.interval_text(st['interval'])} | "
                     f"{st['verdict']} |")
    return lines


def _claim_changes(short: dict, long: dict, lr: str) -> list[str]:
    lines = ["| claim | seeds | 5 M: mean [95% t interval] | 5 M verdict | 20 M: mean "
             "[95% t interval] | 20 M verdict | changed |", "|---|---|---|---|---|---|---|"]
    headline = [("full model > Baseline (the paper's headline, +12.9)", f"org_il+tpn@{lr}",
                 "baseline", 1)]
    for name, row, ref, sign in claims(lr) + headline:
        d_long, seeds = stats.paired(long, row, ref)
        d_short, seeds_short = stats.paired(short, row, ref)
        if not seeds or seeds_short != seeds:
            continue
        a, b = stats.statistics(d_short, sign), stats.statistics(d_long, sign)
        lines.append(f"| {name} | {','.join(seeds)} | {a['mean']:+.1f} "
                     f"{stats.interval_text(a['interval'])} | {a['verdict']} | "
                     f"{b['mean']:+.1f} {stats.interval_text(b['interval'])} | "
                     f"{b['verdict']} | {'no' if a['verdict'] == b['verdict'] else 'yes'} |")
    return lines


def _curve_lines(out: Path, seeds: list[str]) -> list[str]:
    head = " | ".join(f"val at {m // 1_000_000} M" for m in MILESTONES)
    lines = [f"| row | seeds | {head} | 20 M - 15 M per seed | mean [95% t interval] |",
             "|---|---|" + "---|" * len(MILESTONES) + "---|---|"]
    for row in NAV_ROWS:
        runs = [out / "runs" / f"{row}-s{s}" for s in seeds]
        v = np.array([[100 * float(val_at(r, m)["success"]) for m in MILESTONES]
                      for r in runs])                                      # (seeds, M)
        d = v[:, -1] - v[:, -2]
        st = stats.statistics(d, 1)
        lines.append(f"| {row} | {','.join(seeds)} | "
                     + " | ".join(f"{x:.1f}" for x in v.mean(0))
                     + f" | {', '.join(f'{x:+.1f}' for x in d)} | {st['mean']:+.1f} "
                     f"{stats.interval_text(st['interval'])} |")
    return lines


def _adjacency_section(results: Path, long_dir: Path, seeds: list[str]) -> list[str]:
    lines = ["| row | budget | seed | anchor AUC | anchor pairs above the mean | p-value |",
             "|---|---|---|---|---|---|"]
    for row in ("org", "org_il"):
        for budget, where in (("5 M", results / f"rerun_{row}_5m"), ("20 M", long_dir)):
            lines += adjacency_lines(f"| {row} | {budget} |",
                                     adjacency_reports(where, row, seeds))
    return lines


def budget_20m_markdown(results: Path, short_dir: Path | None = None,
                        long_dir: Path | None = None) -> str:
    """table_20m/budget.md: each row at 5 M and 20 M, the claims on the same seeds at
    both, the val curves, and the learned adjacency at both budgets (short_dir and
    long_dir default to results/SHORT and results/LONG)."""
    short_dir = short_dir or results / SHORT
    long_dir = long_dir or results / LONG
    spec, long, _ = read_table_dir(long_dir)
    seeds = [str(s) for s in spec["seeds"]]
    _, short, _ = read_table_dir(short_dir)
    short = _restrict(short, seeds)
    rows = [r for r in spec["rows"] if all(s in long.get(r, {}) for s in seeds)]
    long = {r: long[r] for r in rows}
    return "\n".join(
        [f"# 5 M against 20 M env steps (seeds {','.join(seeds)}; test success, points)",
         "", "Written by `python experiments/budget_20m.py` from "
         f"`{short_dir.name}` and `{long_dir.name}`.", "", "## Each row", ""]
        + _row_changes(short, long)
        + ["", "## The claims on the same seeds", ""]
        + _claim_changes(short, long, lr_tag(spec["rows"]))
        + ["", "## The val curves (success, points)", ""]
        + _curve_lines(long_dir, seeds)
        + ["", "## The learned adjacency (anchor pairs against other same-room-type pairs; "
           "AUC 0.5 = chance)", ""]
        + _adjacency_section(results, long_dir, seeds)) + "\n"


# ---- the TPN's stage-2 budget on val (tpn_budget/budget.json, budget.md) ---------------

def tpn_budget_gain(a: dict, b: dict) -> tuple[float, float, float]:
    """Success of a minus b in points over the same val episodes (per-episode arrays, as
    runs.read_results gives) -> (mean, low, high): the 95% t interval (stats.t_interval)
    of the mean per-episode difference."""
    d = stats.by_episode(a["success"], b["success"])
    return (float(d.mean()), *stats.t_interval(d))


def tpn_budget_table(summary: dict) -> str:
    """budget.md: per base and stage-2 budget, the stage-2 val cross-entropy and accuracy,
    val success at each test-time lr, the lr chosen on val and its gain over the base
    alone with its interval (the lr was chosen on the same episodes: optimistic)."""
    lrs = summary["lrs"]
    head = ["base", "stage-2 episodes", "val CE", "val accuracy", "base alone"] + \
        [f"lr {lr:g}" for lr in lrs] + ["lr chosen on val", "gain [95% interval]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for base, b in summary["bases"].items():
        for budget, t in b["budgets"].items():
            cells = [base, f"{int(budget):,}", f"{t['val_ce']:.3f}",
                     f"{100 * t['val_accuracy']:.1f}", f"{100 * b['alone']:.1f}"] + \
                [f"{100 * t['success'][f'{lr:g}']:.1f}" for lr in lrs] + \
                [f"{t['chosen']:g}", "{:+.1f} [{:+.1f}, {:+.1f}]".format(*t["gain"])]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _budget_entry(base_dir: Path, budget: int, lrs, alone: dict) -> dict:
    """One (base, budget) cell of the summary, from the TPN run's files (`alone`: the
    base's per-episode val arrays)."""
    tpn_dir = base_dir / f"tpn-{budget}"
    res = {f"{lr:g}": read_results(tpn_dir / f"val_tpn@{lr:g}.json") for lr in lrs}
    chosen = max(res, key=lambda k: (res[k][0]["success"], res[k][0]["spl"]))
    v = last_val(tpn_dir, "episodes")
    return {"val_ce": v.get("ce", float("nan")),
            "val_accuracy": v.get("accuracy", float("nan")),
            "success": {k: overall["success"] for k, (overall, _) in res.items()},
            "spl": {k: overall["spl"] for k, (overall, _) in res.items()},
            "chosen": float(chosen), "gain": list(tpn_budget_gain(res[chosen][1], alone))}


def tpn_budget_summary(out: Path, seed: int, lrs, done: dict[str, list[int]],
                       config: dict) -> dict:
    """The summary of the finished (base, budgets) in `done`, read from the run files
    (every results JSON checked against its per-episode outcomes)."""
    summary = {"seed": seed, "lrs": list(lrs), "config": config, "bases": {}}
    for base, budgets in done.items():
        base_dir = out / "runs" / f"{base}-s{seed}"
        overall, alone = read_results(base_dir / "val_results.json")
        summary["bases"][base] = {"alone": overall["success"], "budgets": {
            str(b): _budget_entry(base_dir, b, lrs, alone) for b in budgets}}
    return summary


def tpn_budget_pages(out: Path) -> dict[Path, str]:
    """OUT/budget.json and OUT/budget.md recomputed from the run files, for the sweep
    that OUT/budget.json records (its seed, lrs, bases, budgets and config)."""
    path = out / "budget.json"
    doc = read_object(read_json(path, "a budget JSON"), path)
    try:
        args = (doc["seed"], doc["lrs"], {b: [int(x) for x in e["budgets"]]
                                          for b, e in doc["bases"].items()}, doc["config"])
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise ValueError(f"{path}: malformed ({type(err).__name__}: {err})") from None
    summary = tpn_budget_summary(out, *args)
    return {path: json.dumps(summary, indent=1), out / "budget.md": tpn_budget_table(summary)}
