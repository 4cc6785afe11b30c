"""Pictures of trained runs: the ORG adjacency as a category heat map; learning curves;
one episode from above; the TPN memory's attention over an episode.

    python -m orgnav_jax.plots episode RUN_DIR [--episode K] [--split test] [--out PNG]

draws the room of episode K of the split's seeded episode set (or of --episodes FILE)
from above: every position, where the target is in view, the agent's path from start to
end (green star: success; red: wrong Done or timeout), its deadlock steps (x) and, for a
TPN run, the steps where the test-time update changed the policy (orange circles).

    python -m orgnav_jax.plots tpn-attention TPN_RUN_DIR [--episode K] [--step S] [--out PNG]

draws the paper's Fig. 3 (left) for episode K of a TPN run: the weights the TPN's read
put on each earlier step's memory slot, at every step (a heat map, darker = more weight,
with the deadlock and update steps marked), and at step S (default: the first update)
as bars labelled with the action taken there.

    python -m orgnav_jax.plots adjacency RUN_DIR [--out PNG] [--latest] [--json]

draws the learned adjacency A (C x C) of an `org` run (or the fixed prior graph of a `dsp`
run) with category names on both axes, marks the generator's co-occurrence pairs
(scenes/synthetic/catalog.py ANCHORS) and prints whether A ranks them above the other pairs.

    python -m orgnav_jax.plots curves RUN_DIR... [--out PNG] [--metrics success spl]
                                      [--band minmax|std]

draws val success and SPL (one panel each) against env steps from each run's
metrics.jsonl: runs are grouped into rows by directory name without its -s<seed> suffix
(runs/baseline-s0, runs/baseline-s1 -> "baseline"; or name the row: ROW=DIR), one line
per row = the mean over its seeds at the env steps they share, with a band (min-max over
seeds, or mean +- std). Prints per row: seeds, final and best val success.
"""

from orgnav_jax.plots.adjacency import (anchor_pair_report, anchor_pairs, find_adjacency,
                                        format_report, plot_adjacency, run_adjacency)
from orgnav_jax.plots.common import default_out, save_png
from orgnav_jax.plots.curves import (BANDS, CurveError, aggregate, curves_summary,
                                     group_runs, load_curves, plot_curves, read_val_curve,
                                     row_of)
from orgnav_jax.plots.episodes import (plot_episode, plot_tpn_attention, tpn_attention,
                                       trace_run_episode)
from orgnav_jax.plots.cli import main

__all__ = ["anchor_pair_report", "anchor_pairs", "find_adjacency", "format_report",
           "plot_adjacency", "run_adjacency", "default_out", "save_png", "BANDS",
           "CurveError", "aggregate", "curves_summary", "group_runs", "load_curves",
           "plot_curves", "read_val_curve", "row_of", "plot_episode", "plot_tpn_attention",
           "tpn_attention", "trace_run_episode", "main"]
