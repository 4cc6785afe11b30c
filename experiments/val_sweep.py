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
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from orgnav_jax import api
from orgnav_jax.errors import run_cli
from orgnav_jax.train import PRETRAIN_PIPELINES
from orgnav_jax.training.run_dir import METRICS_FILE, is_run_dir, read_metrics
from orgnav_jax.training.config import TrainConfig, get_config, load_config


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


def best_val(run_dir: Path, up_to: int) -> dict:
    """The best val record of a run up to `up_to` env steps (metrics.jsonl, by success
    then SPL, as the trainer picks its best checkpoint)."""
    val = [r for r in read_metrics(run_dir)          # the typed reader of metrics.jsonl
           if r["kind"] == "val" and r["env_steps"] <= up_to]
    if not val:
        raise ValueError(f"{run_dir / METRICS_FILE}: no val record up to env step {up_to:,}")
    for r in val:
        missing = [k for k in ("success", "spl") if k not in r]
        if missing:
            raise ValueError(f"{run_dir / METRICS_FILE}: the val record at env step "
                             f"{r['env_steps']:,} lacks field(s) {missing}")
    return max(val, key=lambda r: (r["success"], r["spl"]))


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


def write_summary(out: Path, name: str, results: dict) -> str:
    lines = ["| variant | seeds | best val success | best val SPL | at env steps |",
             "|---|---|---|---|---|"]
    for variant, by_seed in results.items():
        s = 100 * np.array([r["success"] for r in by_seed.values()])
        p = 100 * np.array([r["spl"] for r in by_seed.values()])
        steps = ", ".join(f"{r['env_steps'] / 1e6:.2f} M" for r in by_seed.values())
        lines.append(f"| {variant} | {len(s)} | {s.mean():.1f} ± {s.std():.1f} | "
                     f"{p.mean():.1f} ± {p.std():.1f} | {steps} |")
    text = "\n".join(lines) + "\n"
    (out / f"{name}.md").write_text(text)
    (out / f"{name}.json").write_text(json.dumps(results, indent=1))
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--name", required=True, help="the sweep's name (output file names)")
    ap.add_argument("--variants", nargs="+", required=True, type=parse_variant)
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--total-env-steps", type=int, default=5_000_000)
    ap.add_argument("--out", default="experiments/results/sweeps")
    ap.add_argument("--runs", default=None,
                    help="where the runs go (default OUT/runs); the table's runs directory "
                         "lets a table extend the chosen variant's run to its budget")
    args = ap.parse_args(argv)
    from orgnav_jax.training.loop import train
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    saved = out / f"{args.name}.json"
    results = json.loads(saved.read_text()) if saved.exists() else {}
    for seed in args.seeds:
        for name, row, overrides in args.variants:
            run_dir = Path(args.runs if args.runs is not None else out / "runs") / \
                f"{name}-s{seed}"
            pre = run_dir.with_name(f"{name}-pretrain-s{seed}") \
                if row in PRETRAIN_PIPELINES and "pretrained" not in overrides else None
            cfg = get_config(row, **{**overrides, "seed": seed, "run_dir": str(run_dir),
                                     "total_env_steps": args.total_env_steps,
                                     **({"pretrained": str(pre)} if pre else {})})
            print(f"{name} seed {seed}: {row} {overrides}", flush=True)
            if pre and not is_run_dir(run_dir):     # VTNet: its pre-training first
                api.pretrain_for(cfg, pre, progress=sys.stderr.isatty())
            if needs_training(run_dir, args.total_env_steps):
                train(cfg, resume=is_run_dir(run_dir), progress=sys.stderr.isatty())
            record = best_val(run_dir, args.total_env_steps + cfg.steps_per_update *
                              cfg.updates_per_chunk)
            results.setdefault(name, {})[str(seed)] = {
                k: record[k] for k in ("success", "spl", "env_steps")} | {
                "row": row, "overrides": overrides}
            print(write_summary(out, args.name, results), flush=True)


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
