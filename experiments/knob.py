"""Issue 24's co-occurrence knob: does ORG's gain over the Baseline grow with how often
the generator puts an anchored object by its anchor (P)?

    python experiments/knob.py --adjacency DIR/runs/org-s0 ...   # from checkpoints
    python experiments/knob.py                  # writes experiments/results/before_parity/knob/
    python experiments/knob.py --check          # recompute knob.md; exit 1 on a difference

The points (POINTS): P = 0 and P = 1 are run_table.py outputs of their own
(experiments/tables/knob_p0.json, knob_p1.json: Baseline and ORG, seeds 0-2, 5 M env
steps, on `scenes build --anchor-probability P` sets); P = 0.85, the default, is the 5 M
table's Baseline and ORG rows on the same seeds. Per point: test success of both rows,
the paired difference ORG - Baseline per seed with its 95% t interval and verdict
(claims.statistics), and the learned adjacency's anchor statistic of every ORG run that
has an adjacency.json beside its files; and that statistic for the 5 M table's ORG and
ORG + IL runs (seeds 0-4, TABLE_ADJACENCY).

--adjacency RUN... writes RUN/adjacency.json from the run's best-on-val checkpoint: the
learned 22 x 22 matrix A and plots.adjacency.anchor_pair_report(A) (anchor-pair p-value,
anchor_auc: the chance that an anchor pair's value exceeds another same-room-type
pair's, 0.5 = chance). The matrix is kept so that --check recomputes the report from it
without the checkpoint (checkpoints stay out of git).

Writes OUT/knob.md (the tables) and OUT/knob.png (the gain against P, with the
intervals and each seed).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import claims  # noqa: E402  (sibling script: the paired statistics, reading a table dir)
from orgnav_jax.constants import NUM_CATEGORIES  # noqa: E402
from orgnav_jax.errors import read_field, read_json, read_object, run_cli  # noqa: E402

# The knob was measured before network parity (issue 39): its points and the 5 M table
# it compares with are kept in results/before_parity (docs/history/why-gains-small.md).
RESULTS = Path(__file__).resolve().parent / "results" / "before_parity"
OUT = RESULTS / "knob"
# (P, the table directory of its Baseline and ORG runs, the directory whose ORG runs
# carry the adjacency.json of that P; both under RESULTS, named so in knob.md)
POINTS = ((0.0, "knob_p0", "knob_p0"), (0.85, "table_5m", "rerun_org_5m"),
          (1.0, "knob_p1", "knob_p1"))
SEEDS = ("0", "1", "2")            # the knob's seeds; at 0.85 the table's seeds 0-2
# The 5 M table's rows with a learned adjacency, each retrained (bit for bit) to recover
# its checkpoints: (row, the directory whose runs carry adjacency.json), seeds 0-4.
TABLE_ADJACENCY = (("org", "rerun_org_5m"), ("org_il", "rerun_org_il_5m"))
TABLE_SEEDS = ("0", "1", "2", "3", "4")


def write_adjacency(run_dir: Path) -> dict:
    """RUN/adjacency.json: the best-on-val checkpoint's learned adjacency and its report."""
    from orgnav_jax.plots import adjacency
    A, graph = adjacency.run_adjacency(run_dir, best=True)
    if graph != "org":
        raise ValueError(f"{run_dir}: a {graph} model has no learned adjacency")
    doc = {"graph": graph, "A": np.asarray(A, np.float64).round(6).tolist()}
    doc["report"] = adjacency.anchor_pair_report(np.asarray(doc["A"]))
    (run_dir / "adjacency.json").write_text(json.dumps(doc, indent=1))
    return doc


def read_adjacency(path: Path) -> dict:
    """An adjacency.json whose stored report must equal the one its matrix gives."""
    from orgnav_jax.plots import adjacency
    doc = read_object(read_json(path, "an adjacency JSON"), path)
    A = read_field(doc, "A", path)
    try:
        A = np.asarray(A, np.float64)
    except (TypeError, ValueError):
        A = None
    if A is None or A.shape != (NUM_CATEGORIES, NUM_CATEGORIES) or not np.isfinite(A).all():
        raise ValueError(f"{path}: field 'A': expected a {NUM_CATEGORIES} x {NUM_CATEGORIES} "
                         "matrix of finite numbers")
    again = adjacency.anchor_pair_report(A)
    report = read_field(doc, "report", path)
    if json.dumps(again, sort_keys=True) != json.dumps(report, sort_keys=True):
        raise ValueError(f"{path}: the stored report differs from what its matrix gives")
    return report


def point_rows(results: Path = RESULTS) -> list[dict]:
    """Per P: success of both rows, the paired ORG - Baseline statistics, adjacency."""
    rows = []
    for p, table, adj_dir in POINTS:
        entry = {"p": p, "table": table, "adj_dir": adj_dir, "seeds": [], "stats": None}
        if (results / table / "spec.json").exists():
            _, res, _ = claims.read_table_dir(results / table)
            seeds = [s for s in SEEDS if s in res.get("org", {}) and
                     s in res.get("baseline", {})]
            if seeds:
                entry["seeds"] = seeds
                entry["baseline"] = [100 * res["baseline"][s]["success"] for s in seeds]
                entry["org"] = [100 * res["org"][s]["success"] for s in seeds]
                d = np.array(entry["org"]) - np.array(entry["baseline"])
                entry["stats"] = claims.statistics(d, 1)
        entry["adjacency"] = adjacency_reports(results / adj_dir, "org", SEEDS)
        rows.append(entry)
    return rows


def adjacency_reports(table_dir: Path, row: str, seeds) -> dict[str, dict]:
    """{seed: report} of the runs <row>-s<seed> of table_dir that carry adjacency.json."""
    paths = {s: table_dir / "runs" / f"{row}-s{s}" / "adjacency.json" for s in seeds}
    return {s: read_adjacency(p) for s, p in paths.items() if p.exists()}


def table_adjacency(results: Path = RESULTS) -> dict[str, dict[str, dict]]:
    """{row: {seed: report}} of the 5 M table's ORG and ORG + IL runs (TABLE_ADJACENCY)."""
    return {row: adjacency_reports(results / adj_dir, row, TABLE_SEEDS)
            for row, adj_dir in TABLE_ADJACENCY}


def adjacency_lines(head: str, reports: dict[str, dict]) -> list[str]:
    """Table lines of one group of runs: a line per seed and the mean AUC."""
    if not reports:
        return [f"{head} - | not measured yet | | |"]
    lines = [f"{head} {s} | {rep['anchor_auc']:.2f} | {rep['anchor']['higher']} of "
             f"{rep['anchor']['n']} | {rep['anchor']['p_value']:.3f} |"
             for s, rep in reports.items()]
    if len(reports) > 1:
        aucs = [rep["anchor_auc"] for rep in reports.values()]
        significant = sum(rep["anchor"]["p_value"] < 0.05 for rep in reports.values())
        lines.append(f"{head} **mean** | **{np.mean(aucs):.2f}** | p < 0.05 in "
                     f"{significant} of {len(aucs)} | |")
    return lines


def markdown(rows: list[dict], table_runs: dict[str, dict[str, dict]]) -> str:
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
            f"{claims.interval_text(st['interval'])} | {st['verdict']} |")
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


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.6))
    done = [r for r in rows if r["stats"]]
    for r in done:
        ax.scatter([r["p"]] * len(r["stats"]["differences"]), r["stats"]["differences"],
                   color="0.6", s=14, zorder=2)
    if done:
        means = np.array([r["stats"]["mean"] for r in done])
        ivs = np.array([r["stats"]["interval"] for r in done])          # (points, 2)
        ax.errorbar([r["p"] for r in done], means, yerr=[means - ivs[:, 0], ivs[:, 1] - means],
                    fmt="o-", color="C0", capsize=4, zorder=3, label="mean, 95% t interval")
        ax.legend(fontsize=8, loc="upper left")
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("anchor probability P (0.85: the benchmark's default)")
    ax.set_ylabel("ORG - Baseline, test success (points)")
    ax.set_title("ORG's gain against co-occurrence (5 M env steps)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--adjacency", nargs="+", metavar="RUN", default=None,
                    help="write RUN/adjacency.json from each ORG run's checkpoint")
    ap.add_argument("--check", action="store_true",
                    help="recompute knob.md from the runs' files; exit 1 on a difference")
    args = ap.parse_args(argv)
    if args.adjacency:
        for run in map(Path, args.adjacency):
            rep = write_adjacency(run)["report"]
            print(f"{run}/adjacency.json: anchor AUC {rep['anchor_auc']:.2f}, "
                  f"p {rep['anchor']['p_value']:.3f}")
        return 0
    rows = point_rows()
    text = markdown(rows, table_adjacency())
    if args.check:
        path = OUT / "knob.md"
        if not path.exists() or path.read_text() != text:
            print(f"check failed: {path} differs from what the runs' files give",
                  file=sys.stderr)
            return 1
        print(f"{path} agrees with the runs' files")
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "knob.md").write_text(text)
    plot(rows, OUT / "knob.png")
    print(text)
    print(f"wrote {OUT / 'knob.md'} and {OUT / 'knob.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
