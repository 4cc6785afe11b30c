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
(orgnav_jax/tables/stats.py), and the learned adjacency's anchor statistic of every ORG run that
has an adjacency.json beside its files; and that statistic for the 5 M table's ORG and
ORG + IL runs (seeds 0-4, TABLE_ADJACENCY).

--adjacency RUN... writes RUN/adjacency.json from the run's best-on-val checkpoint: the
learned 22 x 22 matrix A and tables/adjacency.anchor_pair_report(A) (anchor-pair p-value,
anchor_auc: the chance that an anchor pair's value exceeds another same-room-type
pair's, 0.5 = chance). The matrix is kept so that --check recomputes the report from it
without the checkpoint (checkpoints stay out of git).

Writes OUT/knob.md (the tables) and OUT/knob.png (the gain against P, with the
intervals and each seed). The page is the tables library's (orgnav_jax/tables/
before_parity.py: knob_points, knob_markdown).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from orgnav_jax.errors import run_cli
from orgnav_jax.plots.adjacency import run_adjacency
from orgnav_jax.safe_write import write_text_atomic
from orgnav_jax.tables import pages
from orgnav_jax.tables.adjacency import ADJACENCY_FILE, adjacency_doc
from orgnav_jax.tables.before_parity import knob_markdown, knob_points, knob_table_adjacency

# The knob was measured before network parity (issue 39): its points and the 5 M table
# it compares with are kept in results/before_parity (docs/history/why-gains-small.md).
RESULTS = Path(__file__).resolve().parent / "results" / "before_parity"
OUT = RESULTS / "knob"


def write_adjacency(run_dir: Path) -> dict:
    """RUN/adjacency.json: the best-on-val checkpoint's learned adjacency and its report."""
    A, graph = run_adjacency(run_dir, best=True)
    if graph != "org":
        raise ValueError(f"{run_dir}: a {graph} model has no learned adjacency")
    doc = adjacency_doc(A, graph)
    write_text_atomic(run_dir / ADJACENCY_FILE, json.dumps(doc, indent=1))
    return doc


def plot(rows: list[dict], path: Path) -> Path:
    import matplotlib                    # (a heavy import only the figure needs)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt      # (after use("Agg"): no display wanted)
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
    rows = knob_points(RESULTS)
    text = knob_markdown(rows, knob_table_adjacency(RESULTS))
    if args.check:
        return pages.regenerate({OUT / "knob.md": text}, check=True)
    pages.write_pages({OUT / "knob.md": text})
    plot(rows, OUT / "knob.png")
    print(text)
    print(f"wrote {OUT / 'knob.md'} and {OUT / 'knob.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
