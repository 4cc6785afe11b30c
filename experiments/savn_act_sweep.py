"""Choose SAVN's test-time actions on the val split (never on test): greedy or sampled.

    python experiments/savn_act_sweep.py experiments/results/val_choices/runs/dsavn-lr1e-4-k6-s100 \\
        --out experiments/results/val_choices/savn_act.json

Evaluates each SAVN run's best-on-val checkpoint on the val episodes (250 per room type)
with greedy actions and with actions sampled from the policy (the release's,
agents/agent.py:120), the same inner steps either way, and writes a JSON in
val_sweep.py's form ({act: {seed: {success, spl, env_steps, row, overrides}}}) that
experiments/val_choices.py reads; each evaluation's results file goes beside it
(OUT_STEM.<run>.<act>.json).

Checked before anything is evaluated or written (one line, exit 2): every run (a SAVN
run directory), --out (new, or a JSON of this form, which is replaced) and every
evaluation's results file (new, or an evaluation results JSON): a file of the user's is
never overwritten.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.errors import UserError, run_cli
from orgnav_jax.safe_write import check_output_file, write_text_atomic
from orgnav_jax.training.config import load_config

ACTS = ("greedy", "sample")
SWEEP = "a sweep JSON {act: {seed: {success, spl, ...}}} of experiments/savn_act_sweep.py"


def is_sweep_json(path: str | Path) -> bool:
    """Whether `path` holds a JSON of this script's form ({act: {seed: record}}, acts of
    ACTS, records objects with success and spl)."""
    try:
        doc = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and set(doc) <= set(ACTS) and all(
        isinstance(by_seed, dict) and all(isinstance(r, dict) and {"success", "spl"} <= set(r)
                                          for r in by_seed.values())
        for by_seed in doc.values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="SAVN or D-SAVN training run directories")
    ap.add_argument("--out", required=True, help="the sweep's JSON")
    args = ap.parse_args(argv)
    if not args.out.strip():
        raise UserError("--out is empty: expected a path")
    out = Path(args.out)
    configs = {}
    for run in args.runs:                    # every run, before any evaluation
        cfg = load_config(run)
        if not cfg.savn:
            raise UserError(f"{run}: a {cfg.model} run without SAVN: expected a SAVN run")
        configs[run] = cfg
    seeds = [cfg.seed for cfg in configs.values()]
    same = sorted({s for s in seeds if seeds.count(s) > 1})
    if same:         # the record holds one run per seed
        raise UserError(f"runs: two runs of seed {same[0]} (the sweep records one per seed)")
    names = [Path(run).name for run in args.runs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise UserError(f"runs: two runs named {twice[0]} (their results files would be one)")
    check_output_file(out, is_sweep_json, SWEEP)
    files = {(run, act): out.with_name(f"{out.stem}.{Path(run).name}.{act}.json")
             for run in args.runs for act in ACTS}
    for (run, act), path in files.items():
        check_output_file(path, api.is_results_json, api.RESULTS,
                          option=f"the results file of {Path(run).name} ({act})",
                          inputs=(out,))
    results: dict = {}
    for run, cfg in configs.items():
        for act in ACTS:
            res = api.evaluate_run(run, "val", savn_act=act, progress=False,
                                   out=files[run, act])
            results.setdefault(act, {})[str(cfg.seed)] = {
                "success": res["overall"]["success"], "spl": res["overall"]["spl"],
                "env_steps": cfg.total_env_steps, "row": "dsavn" if cfg.model == "baseline"
                else "savn", "overrides": {"savn_act": act}, "run": str(run)}
            write_text_atomic(out, json.dumps(results, indent=1))
            print(f"{Path(run).name} {act}: success {100 * res['overall']['success']:.1f} "
                  f"spl {100 * res['overall']['spl']:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
