"""The budget campaign's page: the convergence rule (tables/convergence.py) on each row
of runs, their val success by span of env steps, and a finished table's rows by tenth of
their budget (experiments/convergence.py writes or --checks it); and a table's
convergence.md, the rule on each of its trained rows (a spec with "converged": true).

    rows = rows_of(run_dirs)                  # {row: [its seeds' run directories]}
    lines = verdict_lines(rows)               # the rule per row, in words
    text = report(out, table_5m, root)        # experiments/results/convergence/report.md
    text, not_converged = table_convergence(out, spec)    # OUT/convergence.md
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from orgnav_jax.tables.convergence import (
    CONFIRM, MIN_EVALUATIONS, MIN_SEEDS, MIN_VAL_EPISODES, TOLERANCE, applicable, converged,
    SeedMeanCurve, Verdict, converged_at, read_val_curve, seed_mean_curve, seed_span_means,
    span_means,
)
from orgnav_jax.tables.layout import run_dir
from orgnav_jax.tables.rows import RANDOM, Row
from orgnav_jax.training.config import get_config, load_config
from orgnav_jax.training.run_dir import METRICS_FILE, read_metrics

SEED_SUFFIX = re.compile(r"-s\d+$")
TABLE_5M_ROWS = ("baseline", "org", "il", "org_il", "we", "dsp", "dsavn", "savn")
# the rows whose convergence sets the table's budget (docs/results.md, issue 65 step 2)
BUDGET_ROWS = ("baseline", "we", "org_il")
BUDGET_ROUND = 1_000_000                 # the table's budget: rounded up to whole millions
SPANS_M = (0, 1, 2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 18, 20, 25, 30, 40, 50, 60)


def rows_of(run_dirs) -> dict[str, list[Path]]:
    """Run directories -> {row: [its seeds' directories]}, seeds in name order: a row is
    the runs of one directory whose names differ only in -s<seed> (named by that name,
    or by its path where the runs come from several directories)."""
    rows: dict[str, list[Path]] = {}
    for d in map(Path, run_dirs):
        rows.setdefault(str(d.parent / SEED_SUFFIX.sub("", d.name)), []).append(d)
    short = len({Path(k).parent for k in rows}) == 1
    return {(Path(k).name if short else k): sorted(v) for k, v in rows.items()}


def verdict_lines(rows: dict[str, list[Path]]) -> list[str]:
    """One line per row: the rule at its last evaluation and where it first held."""
    out, curves = [], row_curves(rows)
    firsts = first_converged(curves)
    for row, curve in curves.items():
        why = applicable(curve)
        if why:
            out.append(f"{row}: not judged ({why})")
            continue
        v, first = converged(curve), firsts[row]
        where = (f"first said converged at {first.env_steps:,} env steps (B = "
                 f"{first.budget:,})" if first else "has not said converged yet")
        out.append(f"{row}: {'converged' if v.converged else 'not converged'} ({v.why}); "
                   f"{where}")
    return out


def setting(run_dir: Path) -> str:
    """A run's training setting in a few words (from its config.json)."""
    c = load_config(run_dir)
    return (f"{c.model}, IL {c.il}, {c.num_envs} envs x {c.rollout_len} steps, lr {c.lr:g}")


def row_curves(rows: dict[str, list[Path]]) -> dict[str, SeedMeanCurve]:
    """Each row's seed-mean val curve, read once for every table of the page."""
    return {row: seed_mean_curve([read_val_curve(d) for d in dirs])
            for row, dirs in rows.items()}


def rule_text() -> str:
    """The rule in one sentence, for the pages' headers."""
    return ("The rule (docs/results.md, \"When a row has converged\"; "
            "`orgnav_jax/tables/convergence.py`): seed-mean val success of at least "
            f"{MIN_SEEDS} seeds in one program, {MIN_VAL_EPISODES:,}-episode val "
            f"evaluations, at least {MIN_EVALUATIONS} of them; the quarter test holds when "
            f"the last quarter of the evaluations is within {TOLERANCE:g} point of the "
            "quarter before; the row has converged at B when the quarter test has held at "
            f"every evaluation from B to {CONFIRM:g} B.")


def quarter_cells(v: Verdict) -> str:
    """A verdict's last quarter | quarter before | change, as table cells ('-' where the
    curve is too short to have quarters)."""
    fmt = lambda x: "-" if x is None else f"{x:.1f}"
    change = "-" if v.change is None else f"{v.change:+.1f}"
    return f"{fmt(v.last_quarter)} | {fmt(v.quarter_before)} | {change}"


def rule_state(v: Verdict) -> str:
    """The rule's verdict in words: converged, too short, quarter test holds, not
    confirmed yet, or not converged."""
    return "converged" if v.converged else (
        "too short" if v.change is None else
        "quarter test holds, not confirmed yet" if abs(v.change) <= TOLERANCE
        else "not converged")


def first_converged(curves: dict[str, SeedMeanCurve]) -> dict[str, Verdict | None]:
    """Each row's converged_at (where the rule first said converged; None where it never
    did or cannot judge the curve), computed once for the page's tables."""
    return {row: None if applicable(c) else converged_at(c) for row, c in curves.items()}


def campaign_table(rows: dict[str, list[Path]], curves: dict[str, SeedMeanCurve],
                   firsts: dict[str, Verdict | None]) -> list[str]:
    lines = ["| row | setting | seeds | evaluations | to env step | last quarter | quarter "
             "before | change | rule | B (said at) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row, dirs in rows.items():
        curve = curves[row]
        seeds = ", ".join(d.name.rpartition("-s")[2] for d in dirs)
        head = f"| {row} | {setting(dirs[0])} | {seeds} | {len(curve.steps)} | " \
               f"{int(curve.steps[-1]):,} |"
        why = applicable(curve)
        if why:
            lines.append(f"{head} | | | not judged: {why} | |")
            continue
        v, first = converged(curve), firsts[row]
        lines.append(f"{head} {quarter_cells(v)} | {rule_state(v)} | "
                     f"{f'{first.budget:,} (at {first.env_steps:,})' if first else '-'} |")
    return lines


def span_table(curves: dict[str, SeedMeanCurve], edges_m) -> list[str]:
    """Seed-mean val success (points) per span of env steps (millions), spans that some
    row reached."""
    last = max(int(c.steps[-1]) for c in curves.values())
    edges = [e for e in edges_m if e * 1_000_000 < last] + [
        next((e for e in edges_m if e * 1_000_000 >= last), edges_m[-1])]
    edges = [e * 1_000_000 for e in edges]
    head = [f"{lo // 1_000_000}-{hi // 1_000_000} M" for lo, hi in zip(edges[:-1], edges[1:])]
    lines = ["| row | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for row, c in curves.items():
        cells = ["" if m is None else f"{m:.1f}" for m in span_means(c, edges)]
        lines.append(f"| {row} | " + " | ".join(cells) + " |")
    return lines


def tenths_table(table_dir: Path, rows: tuple[str, ...]) -> list[str]:
    """A table's rows by tenth of their budget: each seed's mean val success (points)
    over the evaluations in each tenth of its run, averaged over the seeds (SAVN's
    evaluation steps differ by seed), and the gain of the last fifth over the one
    before."""
    lines = ["| row | seeds | " + " | ".join(f"{i}" for i in range(1, 11)) +
             " | last fifth - fifth before |", "|---|---|" + "---|" * 11]
    for row in rows:
        dirs = sorted(p for p in (table_dir / "runs").glob(f"{row}-s*") if p.is_dir())
        if not dirs:
            continue
        curves = [read_val_curve(d) for d in dirs]
        tenths = seed_span_means(curves, 10)
        fifths = seed_span_means(curves, 5)
        cells = ["" if m is None else f"{m:.1f}" for m in tenths]
        lines.append(f"| {row} | {len(dirs)} | " + " | ".join(cells) +
                     f" | {fifths[-1] - fifths[-2]:+.1f} |")
    return lines


def has_val(run: Path) -> bool:
    """Whether a run directory's metrics.jsonl holds a val evaluation (its typed reader: a
    damaged line is an error naming the file, a line cut by a kill is skipped)."""
    return (run / METRICS_FILE).is_file() and any(
        r["kind"] == "val" for r in read_metrics(run, skip_broken=True))


def table_budget(firsts: dict[str, Verdict | None]) -> tuple[int | None, str]:
    """The table's budget (docs/results.md) from the rows' first_converged: the largest
    env step at which the rule first said converged among BUDGET_ROWS, rounded up to
    whole BUDGET_ROUND -> (it, one sentence), or (None, which rows it waits for)."""
    said = {row: firsts.get(row) for row in BUDGET_ROWS}
    waiting = [row for row, v in said.items() if v is None]
    if waiting:
        return None, (f"Not fixed yet: {', '.join(waiting)} not converged by the rule "
                      f"(the budget waits for {', '.join(BUDGET_ROWS)}).")
    last = max(v.env_steps for v in said.values())
    budget = -(-last // BUDGET_ROUND) * BUDGET_ROUND
    return budget, (f"**{budget:,} env steps**: the largest env step where the rule said "
                    f"converged ({', '.join(f'{r} {v.env_steps:,}' for r, v in said.items())}"
                    f"), rounded up to whole millions.")


def campaign_rows(out: Path) -> dict[str, list[Path]]:
    """The campaign's rows whose runs have logged a val evaluation."""
    runs = sorted(p for p in (out / "runs").glob("*-s*") if has_val(p))
    return rows_of(runs) if runs else {}


def report(out: Path, table_5m: Path, root: Path) -> str:
    """The campaign's page (report.md) from the runs in out/runs and the 5 M table's runs
    in table_5m/runs; paths shown relative to the repository `root`."""
    rows = campaign_rows(out)
    text = ["# Convergence: the budget and the fastest setting, on val", "",
            "Written by `python experiments/convergence.py report` from the runs' committed "
            f"files (`--check` recomputes it). {rule_text()} Runs: calibrated preset, "
            "seeds 100-101, val every 204,800 env steps (`runs/`).", ""]
    if rows:
        curves = row_curves(rows)
        firsts = first_converged(curves)
        text += ["## The rule on each row", "", *campaign_table(rows, curves, firsts), "",
                 f"The table's budget: {table_budget(firsts)[1]}", "",
                 "## Val success by span of env steps (seed mean, points)", "",
                 *span_table(curves, SPANS_M), ""]
    text += ["## The 5 M calibrated table's rows, by tenth of their budget", "",
             "Seed-mean val success (points; 200-episode evaluations, seeds 0-4) over each "
             "tenth of the 5,017,600 env steps, from "
             f"`{table_5m.relative_to(root).as_posix()}/runs/*/metrics.jsonl`:", "",
             *tenths_table(table_5m, TABLE_5M_ROWS), ""]
    return "\n".join(text)


def table_rows(out: Path, spec: dict) -> dict[str, list[Path]]:
    """A table's trained navigation rows (not random; of a TPN row its base row, each
    once), in the spec's order -> the run directories OUT/runs/ROW-sS of its seeds that
    have logged a val evaluation."""
    bases = dict.fromkeys(Row.of(name).base for name in spec["rows"])
    return {base: [d for d in (run_dir(out, base, s) for s in spec["seeds"]) if has_val(d)]
            for base in bases if base != RANDOM}


def table_row_rule(dirs: list[Path]) -> tuple[str, bool]:
    """A table row's run directories -> its convergence.md cells after the row's name
    (seeds | evaluations | to env step | last quarter | quarter before | change | verdict)
    and whether it has converged by the rule at its last shared evaluation."""
    if not dirs:
        return "| | | | | | no runs yet", False
    seeds = ", ".join(d.name.rpartition("-s")[2] for d in dirs)
    # runs named by their directory: the page reads the same wherever the table lies
    curves = [dataclasses.replace(read_val_curve(d), where=d.name) for d in dirs]
    try:
        curve = seed_mean_curve(curves)
    except ValueError as err:                 # the runs share no val evaluation step
        return f"{seeds} | | | | | | not judged: {err}", False
    head = f"{seeds} | {len(curve.steps)} | {int(curve.steps[-1]):,}"
    why = applicable(curve)
    if why:
        return f"{head} | | | | not judged: {why}", False
    v = converged(curve)
    if v.converged:
        verdict = f"converged (B' = {v.budget:,})"
    else:                                     # too short, not confirmed yet: said in ()
        state = rule_state(v)
        verdict = "not converged" + ("" if state == "not converged" else f" ({state})")
    return f"{head} | {quarter_cells(v)} | {verdict}", v.converged


def table_convergence(out: Path, spec: dict) -> tuple[str, list[str]]:
    """A table whose spec has "converged": true -> its convergence.md (the rule on each
    trained navigation row at its last val evaluation, from OUT/runs) and the trained
    rows that have not converged by it (listed in claims.md; a row with no runs yet is
    not among them: its claims are not measured)."""
    lines = ["# The convergence rule on each trained row", "",
             "Written by `python experiments/claims.py OUT` from the runs' val curves "
             "(`--check` recomputes it); the spec's `\"converged\": true` asks every row "
             "trained for the table's budget to pass the rule at its last val evaluation. "
             f"{rule_text()} B' is that B for the row; a TPN row is judged by its base "
             "row's runs; a row that has not converged is named in claims.md, and its "
             "claims are not judged at convergence.", "",
             "| row | seeds | evaluations | to env step | last quarter | quarter before | "
             "change | verdict |", "|---|---|---|---|---|---|---|---|"]
    if "extends" in spec:
        cap = get_config("baseline", **spec["config"]).total_env_steps
        lines[2:2] = [f"This table extends `{spec['extends']}` (the spec's \"extends\"): its "
                      "rows that converged there, or that the rule cannot judge (SAVN: one "
                      "seed per program), are carried over with their runs and test results; "
                      "the others trained on from its runs under the stop criterion, to at most "
                      f"{cap:,} env steps, and were tested again from their best-on-val "
                      "checkpoint over the whole run (tables/extend.py).", ""]
    not_converged = []
    for row, dirs in table_rows(out, spec).items():
        cells, ok = table_row_rule(dirs)
        lines.append(f"| {row} | {cells} |")
        if dirs and not ok:
            not_converged.append(row)
    return "\n".join(lines) + "\n", not_converged
