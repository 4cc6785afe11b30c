"""Choose TPN's test-time learning rate on the val split (never on test).

    python experiments/tpn_lr_sweep.py experiments/results/before_parity/tables/runs/baseline-s0/tpn \\
        --lrs 1e-4 1e-3 1e-2 1e-1 1 \\
        --out experiments/results/before_parity/tables/lr_sweep_baseline_s0.json

Evaluates the TPN run's base model with test-time updates at each learning rate (and the
base alone, lr 0) on the val episodes (250 per room type) and writes a JSON of the
overall metrics per learning rate, rewritten after each one. Each learning rate's results
file (OUT.lr<lr>.json) is kept: after an interruption the same command reads the ones
already made and evaluates the rest.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from orgnav_jax import api


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tpn_dir")
    ap.add_argument("--lrs", type=float, nargs="+", default=[0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    ap.add_argument("--scope", default="all", help="fast-weight scope (default all)")
    ap.add_argument("--split", default="val")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    out, results = Path(args.out), {}
    for lr in args.lrs:
        one = out.with_suffix(f".lr{lr:g}.json")
        if api.is_results_json(one):     # done before an interruption: read, not re-run
            res = json.loads(one.read_text())
        else:
            res = api.evaluate_run(args.tpn_dir, args.split, tpn_lr=lr, scope=args.scope,
                                   out=one, progress=False)
        results[f"{lr:g}"] = res["overall"]
        out.write_text(json.dumps({"tpn_dir": args.tpn_dir, "split": args.split,
                                   "scope": args.scope, "results": results}, indent=1))
        print(f"lr {lr:g}: success {100 * res['overall']['success']:.1f} "
              f"spl {100 * res['overall']['spl']:.1f}", flush=True)


if __name__ == "__main__":
    main()
