"""Choose training hyperparameters on the val split: train variants of a row, compare their
best val success (the test split is never touched).

    python experiments/val_sweep.py --name dropout --variants \\
        baseline-d0=baseline:dropout=0 baseline-d25=baseline:dropout=0.25 --seeds 0 \\
        --total-env-steps 2048000
    python experiments/val_sweep.py --name il --variants il-cause-w1=il:il_step=cause \\
        il-state-w1=il:il_step=state il-cause-w3=il:il_step=cause,il_weight=3

(experiments/tables/val_sweeps.sh has the sweeps behind the tables' settings.)

A variant is NAME=ROW[:FIELD=VALUE,...] (ROW a training preset, the fields TrainConfig
overrides). Each (variant, seed) trains in OUT/runs/NAME-s<seed> (resumed when it has
checkpoints, skipped when finished: rerun the same command after an interruption). After
every run OUT/<name>.json (every run's best val record) and OUT/<name>.md (best val
success and SPL per variant, mean over seeds) are rewritten. A VTNet variant (row vtnet,
no `pretrained` field) pre-trains first, in OUT/runs/NAME-pretrain-s<seed>, as
`--preset vtnet` does.

    python experiments/val_sweep.py --name il --out experiments/results/val_choices --check

Without --variants, OUT/<name>.md is rewritten from OUT/<name>.json (--check: compared,
exit 1 on a difference). The summary shows mean ± sample std over a variant's seeds (the
tables library's sweeps.summary_text).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.errors import run_cli
from orgnav_jax.tables import pages
from orgnav_jax.tables.rows import PRETRAIN_ROWS
from orgnav_jax.tables.runs import best_val
from orgnav_jax.tables.sweeps import read_sweep, sweep_pages
from orgnav_jax.training import loop
from orgnav_jax.training.config import TrainConfig, get_config, load_config
from orgnav_jax.training.run_dir import METRICS_FILE, is_run_dir, read_metrics


def parse_variant(text: str) -> tuple[str, str, dict]:
    """'NAME=ROW:field=value,field=value' -> (NAME, ROW, {field: typed value})."""
    name, eq, spec = text.partition("=")
    row, _, fields = spec.partition(":")
    if not eq or not name or not row:
        raise argparse.ArgumentTypeError(f"variant {text!r}: expected NAME=ROW[:FIELD=VALUE,...]")
    types = {f.name: type(f.default) for f in dataclasses.fields(TrainConfig)}
    overrides = {}
    for item in filter(None, fields.split(",")):
        key, _, value = item.partition("=")
        if key not in types:
            raise argparse.ArgumentTypeError(f"variant {name!r}: unknown config field {key!r}")
        kind = types[key] if types[key] in (int, float, bool) else str
        overrides[key] = value.lower() in ("1", "true") if kind is bool else kind(value)
    return name, row, overrides


def needs_training(run_dir: Path, total: int) -> bool:
    """Whether a sweep's run must be trained (started or resumed) to `total` env steps:
    not when its metrics already reach it (a run made elsewhere, perhaps without
    checkpoints) or when it was extended beyond the sweep's budget (read as it is)."""
    if not is_run_dir(run_dir):
        return True
    if (run_dir / METRICS_FILE).exists() and max(
            (r["env_steps"] for r in read_metrics(run_dir, skip_broken=True)),
            default=0) >= total:
        return False
    return load_config(run_dir).total_env_steps <= total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--name", required=True, help="the sweep's name (output file names)")
    ap.add_argument("--variants", nargs="+", default=None, type=parse_variant,
                    help="NAME=ROW[:FIELD=VALUE,...]; without: rewrite (or --check) the "
                         "summary of OUT/<name>.json")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--total-env-steps", type=int, default=5_000_000)
    ap.add_argument("--out", default="experiments/results/sweeps")
    ap.add_argument("--runs", default=None,
                    help="where the runs go (default OUT/runs); the table's runs directory "
                         "lets a table extend the chosen variant's run to its budget")
    ap.add_argument("--check", action="store_true",
                    help="without --variants: compare OUT/<name>.md with what OUT/<name>.json "
                         "gives; exit 1 on a difference")
    args = ap.parse_args(argv)
    out = Path(args.out)
    saved = out / f"{args.name}.json"
    if args.variants is None:
        return pages.regenerate(sweep_pages(out, args.name, read_sweep(saved)), args.check)
    if args.check:
        ap.error("--check goes without --variants")
    results = read_sweep(saved) if saved.exists() else {}
    for seed in args.seeds:
        for name, row, overrides in args.variants:
            run_dir = Path(args.runs if args.runs is not None else out / "runs") / \
                f"{name}-s{seed}"
            pre = run_dir.with_name(f"{name}-pretrain-s{seed}") \
                if row in PRETRAIN_ROWS and "pretrained" not in overrides else None
            cfg = get_config(row, **{**overrides, "seed": seed, "run_dir": str(run_dir),
                                     "total_env_steps": args.total_env_steps,
                                     **({"pretrained": str(pre)} if pre else {})})
            print(f"{name} seed {seed}: {row} {overrides}", flush=True)
            if pre and not is_run_dir(run_dir):     # VTNet: its pre-training first
                api.pretrain_for(cfg, pre, progress=sys.stderr.isatty())
            if needs_training(run_dir, args.total_env_steps):
                loop.train(cfg, resume=is_run_dir(run_dir), progress=sys.stderr.isatty())
            record = best_val(run_dir, args.total_env_steps + cfg.steps_per_update *
                              cfg.updates_per_chunk)
            results.setdefault(name, {})[str(seed)] = {
                k: record[k] for k in ("success", "spl", "env_steps")} | {
                "row": row, "overrides": overrides}
            files = sweep_pages(out, args.name, results)
            pages.write_pages(files)
            print(files[out / f"{args.name}.md"], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
