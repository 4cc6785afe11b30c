"""Reproduce a table: several rows (training presets) x seeds, equal budgets, test split.

    python experiments/run_table.py --rows baseline il org org_il il_all --seeds 0 1 2 \\
        --total-env-steps 1000000 --out experiments/results/table1

Each (row, seed) trains in OUT/runs/<row>-s<seed> (skipped when its test results exist,
resumed when it has checkpoints: rerun the same command after an interruption), is
evaluated on the test split (best-on-val checkpoint, 250 episodes per room type), and
the table is rewritten after every run: OUT/results.json (every run) and OUT/table.md
(mean +- std over seeds). Extra `--FIELD VALUE` options apply to every row.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from orgnav_jax import evaluate
from orgnav_jax.training.config import TABLE_ROWS, add_config_arguments, get_config, \
    overrides_from_args

METRICS = ("success", "spl", "success_L5", "spl_L5")


def run_one(row: str, seed: int, out: Path, overrides: dict) -> dict:
    """Train (or resume, or skip) one row and seed -> its test metrics."""
    from orgnav_jax.training.loop import train
    run_dir = out / "runs" / f"{row}-s{seed}"
    results = run_dir / "test_results.json"
    if results.exists():
        return json.loads(results.read_text())["overall"]
    cfg = get_config(row, **{**overrides, "seed": seed, "run_dir": str(run_dir)})
    resume = (run_dir / "checkpoints").exists() and any((run_dir / "checkpoints").iterdir())
    train(cfg, resume=resume, progress=sys.stderr.isatty())
    return evaluate.main(["--checkpoint", str(run_dir), "--split", "test", "--out",
                          str(results), "--quiet"])["overall"]


def write_table(out: Path, results: dict[str, dict[int, dict]]) -> str:
    """results[row][seed] = metrics -> markdown table of mean +- std (percent)."""
    lines = ["| row | seeds | Success | SPL | Success (L>=5) | SPL (L>=5) |",
             "|---|---|---|---|---|---|"]
    for row, by_seed in results.items():
        cells = []
        for m in METRICS:
            v = 100 * np.array([r[m] for r in by_seed.values()])
            cells.append(f"{v.mean():.1f} ± {v.std():.1f}")
        lines.append(f"| {row} | {len(by_seed)} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    (out / "table.md").write_text(text)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", nargs="+", default=["baseline", "il", "org", "org_il", "il_all"],
                    choices=sorted(TABLE_ROWS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--out", default="experiments/results/table1")
    add_config_arguments(ap)
    args = ap.parse_args(argv)
    overrides = {k: v for k, v in overrides_from_args(args).items()
                 if k not in ("seed", "run_dir")}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results: dict[str, dict[int, dict]] = {}
    for seed in args.seeds:                     # seed-major: a partial table covers all rows
        for row in args.rows:
            metrics = run_one(row, seed, out, overrides)
            results.setdefault(row, {})[seed] = metrics
            print(f"{row} seed {seed}: " + ", ".join(f"{m} {100 * metrics[m]:.1f}"
                                                      for m in METRICS), flush=True)
            write_table(out, {r: results[r] for r in args.rows if r in results})
    print(write_table(out, results))


if __name__ == "__main__":
    main()
