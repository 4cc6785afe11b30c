"""python -m orgnav_jax.plots: parse, draw (the modules beside this one), print where."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from orgnav_jax.plots import adjacency, curves, episodes
from orgnav_jax.plots.common import default_out
from orgnav_jax.tpn.config import TEST_TIME_FIELDS, add_tpn_arguments, tpn_overrides_from_args


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m orgnav_jax.plots", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("adjacency", help="heat map of a run's ORG adjacency")
    p.add_argument("run_dir")
    p.add_argument("--out", default=None, help="PNG path (default RUN_DIR/adjacency.png)")
    p.add_argument("--latest", action="store_true",
                   help="use the latest checkpoint instead of the best-on-val one")
    p.add_argument("--json", action="store_true",
                   help="print the report as one JSON object (anchor p-value, anchor_auc, "
                        "pairs) on stdout; the 'wrote' line goes to stderr")
    e = sub.add_parser("episode", help="top view of one episode of a run (path, target, "
                                       "deadlock steps, TPN updates)")
    e.add_argument("run_dir", help="a training run or a TPN (stage 2) run directory")
    t = sub.add_parser("tpn-attention", help="the TPN memory's attention over an episode's "
                                             "earlier steps (the paper's Fig. 3, left)")
    t.add_argument("run_dir", help="a TPN (stage 2) run directory")
    t.add_argument("--step", type=int, default=None, help="the step whose weights the right "
                   "panel shows (default: the first TPN update, else the last step)")
    for sp, png in ((e, "episode-K.png"), (t, "tpn-attention-K.png")):
        sp.add_argument("--episode", type=int, default=0, help="index in the episode set")
        sp.add_argument("--split", choices=("val", "test"), default="test")
        sp.add_argument("--episodes", default=None, help="an episode file (default: the "
                        "seeded set evaluate samples)")
        sp.add_argument("--out", default=None, help=f"PNG path (default RUN_DIR/{png})")
        add_tpn_arguments(sp, TEST_TIME_FIELDS)   # a TPN run's test-time settings
    c = sub.add_parser("curves", help="val learning curves of runs, mean and band over seeds")
    c.add_argument("runs", nargs="+", metavar="RUN_DIR",
                   help="training run directories (or ROW=RUN_DIR); NAME-s<seed> -> row NAME")
    c.add_argument("--out", default=None,
                   help="PNG path (default: FIRST_RUN_DIR/curves.png)")
    c.add_argument("--metrics", nargs="+", default=["success", "spl"],
                   help="val record fields, one panel each (default: success spl)")
    c.add_argument("--band", choices=sorted(curves.BANDS), default="minmax",
                   help="shaded band: min-max over seeds (default) or mean +- std")
    args = ap.parse_args(argv)
    if args.cmd in ("episode", "tpn-attention"):
        kw = dict(episodes_file=args.episodes, test_time=tpn_overrides_from_args(args))
    if args.cmd == "episode":
        out = default_out(args.run_dir, f"episode-{args.episode}.png", args.out)
        out = episodes.plot_episode(args.run_dir, args.episode, args.split, out, **kw)
        print(f"wrote {out}")
        return 0
    if args.cmd == "tpn-attention":
        out = default_out(args.run_dir, f"tpn-attention-{args.episode}.png", args.out)
        out, att = episodes.plot_tpn_attention(args.run_dir, args.episode, args.split, out,
                                      args.step, **kw)
        w = att["attention"][att["step"]]
        top = [f"{i} ({w[i]:.2f})" for i in np.argsort(-w)[:3] if w[i] > 0]
        print(f"wrote {out}\n{int(att['updated'].sum())} TPN updates in "
              f"{len(att['updated'])} steps; step {att['step']} reads most from steps "
              + (", ".join(top) or "none (no earlier step)"))
        return 0
    if args.cmd == "curves":
        rows = curves.group_runs(args.runs)
        out = default_out(next(iter(rows.values()))[0], "curves.png", args.out)
        try:
            curves.plot_curves(rows, out, args.metrics, args.band)
        except curves.CurveError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"wrote {out}")
        return 0
    out = default_out(args.run_dir, "adjacency.png", args.out)
    try:
        A, name = adjacency.run_adjacency(args.run_dir, best=not args.latest)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    title = f"{'learned ORG adjacency' if name == 'org' else 'D-SP prior graph'}: {args.run_dir}"
    adjacency.plot_adjacency(A, out, title)
    report = adjacency.anchor_pair_report(A)
    if args.json:
        print(f"wrote {out}", file=sys.stderr)
        print(json.dumps(dict(report, run_dir=str(args.run_dir), graph=name)))
    else:
        print(f"wrote {out}")
        print(adjacency.format_report(report))
    return 0
