"""Choose TPN's test-time learning rate on the val split (never on test).

    python experiments/tpn_lr_sweep.py experiments/results/before_parity/tables/runs/baseline-s0/tpn \\
        --lrs 1e-4 1e-3 1e-2 1e-1 1 \\
        --out experiments/results/before_parity/tables/lr_sweep_baseline_s0.json

Evaluates the TPN run's base model with test-time updates at each learning rate (and the
base alone, lr 0) on the val episodes (250 per room type) and writes a JSON of the
overall metrics per learning rate ({tpn_dir, split, scope, results: {lr: overall}}),
rewritten after each one; each learning rate's results file is OUT.lr<lr>.json. After an
interruption the same command goes on: the learning rates OUT already records for the
same run, split and scope are kept, the rest are evaluated.

Checked before anything is evaluated or written (one line, exit 2): the TPN run
directory, every learning rate and the scope (as the TPN config checks them), --out (new,
or this sweep's record of the same run, split and scope) and each learning rate's
results file (new, or an evaluation results JSON: nothing else is overwritten).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.errors import UserError, read_json, read_object, run_cli
from orgnav_jax.safe_write import check_output_file, write_text_atomic
from orgnav_jax.tables.sweeps import TPN_SWEEP_KEYS, read_tpn_sweep
from orgnav_jax.tpn.config import get_tpn_config, load_tpn_config

SWEEP = "a TPN learning-rate sweep record of experiments/tpn_lr_sweep.py"


def is_sweep_json(path: str | Path) -> bool:
    """Whether `path` holds a record this script writes (a JSON object of SWEEP_KEYS)."""
    try:
        doc = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and set(TPN_SWEEP_KEYS) <= set(doc) and \
        isinstance(doc["results"], dict)


def _same_dir(a: str, b: str) -> bool:
    try:
        return a == b or Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


def done_before(out: Path, tpn_dir: str, split: str, scope: str) -> dict[str, dict]:
    """The results {lr: overall} a record at `out` holds for this run, split and scope
    ({} when there is none); ValueError when it is the record of another sweep (its
    results are not this one's) or its results are not metrics."""
    if not out.exists():
        return {}
    doc = read_object(read_json(out, SWEEP), out, SWEEP)
    theirs = (doc.get("tpn_dir"), doc.get("split"), doc.get("scope"))
    if not (isinstance(theirs[0], str) and _same_dir(theirs[0], tpn_dir)
            and theirs[1:] == (split, scope)):
        raise UserError(f"--out {out}: the record of another sweep (run {theirs[0]}, split "
                        f"{theirs[1]}, scope {theirs[2]}), not of {tpn_dir} (split {split}, "
                        f"scope {scope}); it is left untouched: choose another --out")
    return read_tpn_sweep(out)             # its results, each read through the typed reader


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tpn_dir", help="a TPN (stage 2) run directory")
    ap.add_argument("--lrs", type=float, nargs="+", default=[0.0, 1e-4, 1e-3, 1e-2, 1e-1, 1.0])
    ap.add_argument("--scope", default="all", help="fast-weight scope (default all)")
    ap.add_argument("--split", default="val", choices=("train", "val", "test"))
    ap.add_argument("--out", required=True, help="the sweep's JSON record")
    args = ap.parse_args(argv)
    if not args.out.strip():
        raise UserError("--out is empty: expected a path")
    saved = load_tpn_config(args.tpn_dir)     # a missing or other run: one line naming it
    keys = [f"{lr:g}" for lr in args.lrs]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise UserError(f"--lrs: {', '.join(twice)} given twice")
    for lr in args.lrs:                       # each learning rate as the TPN config checks it
        get_tpn_config(**{**dataclasses.asdict(saved), "tpn_lr": lr, "scope": args.scope})
    out = Path(args.out)
    check_output_file(out, is_sweep_json, SWEEP)
    files = {lr: out.with_suffix(f".lr{lr:g}.json") for lr in args.lrs}
    for lr, one in files.items():
        check_output_file(one, api.is_results_json, api.RESULTS,
                          option=f"the results file of lr {lr:g}")
    results = done_before(out, args.tpn_dir, args.split, args.scope)
    for lr in args.lrs:
        key = f"{lr:g}"
        if key not in results:       # not recorded before an interruption: evaluate
            res = api.evaluate_run(args.tpn_dir, args.split, tpn_lr=lr, scope=args.scope,
                                   out=files[lr], progress=False)
            results[key] = res["overall"]
            write_text_atomic(out, json.dumps({"tpn_dir": args.tpn_dir, "split": args.split,
                                               "scope": args.scope, "results": results},
                                              indent=1))
        print(f"lr {key}: success {100 * results[key]['success']:.1f} "
              f"spl {100 * results[key]['spl']:.1f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
