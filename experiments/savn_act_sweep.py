"""Choose SAVN's test-time actions on the val split (never on test): greedy or sampled.

    python experiments/savn_act_sweep.py experiments/results/val_choices/runs/dsavn-lr1e-4-k6-s100 \\
        --out experiments/results/val_choices/savn_act.json

Evaluates each SAVN run's best-on-val checkpoint on the val episodes (250 per room type)
with greedy actions and with actions sampled from the policy (the release's,
agents/agent.py:120), the same inner steps either way, and writes a JSON in
val_sweep.py's form ({act: {seed: {success, spl, env_steps, row, overrides}}}) that
experiments/val_choices.py reads; each evaluation's results file goes beside it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.errors import UserError, run_cli
from orgnav_jax.training.config import load_config


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="SAVN or D-SAVN training run directories")
    ap.add_argument("--out", required=True, help="the sweep's JSON")
    args = ap.parse_args(argv)
    out = Path(args.out)
    results: dict = {}
    for run in args.runs:
        cfg = load_config(run)
        if not cfg.savn:
            raise UserError(f"{run}: a {cfg.model} run without SAVN: expected a SAVN run")
        for act in ("greedy", "sample"):
            res = api.evaluate_run(run, "val", savn_act=act, progress=False,
                                   out=out.with_name(f"{out.stem}.{Path(run).name}.{act}.json"))
            results.setdefault(act, {})[str(cfg.seed)] = {
                "success": res["overall"]["success"], "spl": res["overall"]["spl"],
                "env_steps": cfg.total_env_steps, "row": "dsavn" if cfg.model == "baseline"
                else "savn", "overrides": {"savn_act": act}, "run": str(run)}
            out.write_text(json.dumps(results, indent=1))
            print(f"{Path(run).name} {act}: success {100 * res['overall']['success']:.1f} "
                  f"spl {100 * res['overall']['spl']:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
