"""Calibrate the benchmark's perception on the rows the method does not touch (val only).

    python experiments/calibration.py run --setting g3 --row we        # one calibration run
    python experiments/calibration.py run --setting g3d1 --row baseline
    python experiments/calibration.py random [--setting g5v]           # Random on val
    python experiments/calibration.py table                            # writes calibration.md
    python experiments/calibration.py --check                          # recompute; exit 1 if
                                                                       # calibration.md differs
    python experiments/calibration.py --budget 20000000 run --setting g4d1 --row we
                                             # at another budget: its own folder and page

A setting is a set of perception knobs (scenes/synthetic/perception.py) over the `small`
preset: the same rooms, splits, categories and episodes, only the global view and the
detector change; a setting whose name ends in v also lets the evaluation episodes start
with the target in view (tables.calibration.episode_distance). SETTINGS
(orgnav_jax/tables/calibration.py, with the page) lists every setting tried, in the order
tried. `run` builds the setting's scene set once (data/calibration/<setting>, scene seed
0 as every table), trains the row at the table's budget (5 M env steps, dropout 0, seed
100: no table uses it) in OUT/runs/<row>-<setting>, and evaluates its best-on-val
checkpoint on the whole val split (250 episodes per room type) into val_results.json; the
test split is never touched.
Random does not depend on perception: one evaluation on val (seed 100) serves every
setting with the same episodes (runs/random, runs/random-in-view). `--budget N` (env
steps) calibrates at another budget, e.g. the budget at which the rows have converged
(docs/results.md, "When a row has converged"): its runs and page go to OUT/at_N
(runs/<row>-<setting>, calibration.md), Random the evaluations above; the default, 5 M,
is OUT itself.

The table (calibration.md) has, per setting, val success / SPL of Random, WE and the
Baseline beside the targets (AI2-THOR's Table 1 values: Random 8 +- 3, WE 33 +- 5, Baseline
56 +- 5, Baseline SPL 0.32 +- 0.05), and the Baseline's learning curve check: the in-training
val success gained over the last fifth of training (mean of the val evaluations in the last
fifth minus the mean of those in the fifth before; under 2 points = flattened).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.errors import run_cli
from orgnav_jax.scenes import build, save
from orgnav_jax.scenes.sceneset.storage import is_scene_set
from orgnav_jax.scenes.synthetic.perception import Perception
from orgnav_jax.scenes.synthetic.presets import get_preset
from orgnav_jax.tables import pages
from orgnav_jax.tables.calibration import (BUDGET, SEED, SETTINGS, episode_distance,
                                           random_name, table_text)
from orgnav_jax.tables.layout import local_path
from orgnav_jax.tables.provenance import process_provenance, record_provenance, work_recorded
from orgnav_jax.training.config import get_config

OUT = Path(__file__).resolve().parent / "results" / "calibration"


def scenes_dir(setting: str) -> Path:
    return Path("data") / "calibration" / setting


def build_setting(setting: str) -> Path:
    """The setting's scene set (built once, reused)."""
    path = scenes_dir(setting)
    if not is_scene_set(path):
        preset = get_preset("small", episode_distance=episode_distance(setting))
        save(build(preset, 0, perception=Perception(**SETTINGS[setting]), progress=True),
             path)
    return path


def positive_int(text: str) -> int:
    """--budget: a whole number of env steps >= 1 (argparse: one-line error, exit 2)."""
    try:
        value = int(text.replace("_", ""))
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a whole number of env steps "
                                         ">= 1, e.g. 20000000")
    return value


def budget_dir(budget: int) -> Path:
    """Where the calibration at `budget` env steps keeps its runs and page."""
    return OUT if budget == BUDGET else OUT / f"at_{budget}"


def run(setting: str, row: str, budget: int = BUDGET) -> Path:
    """Train `row` on the setting for `budget` env steps (resumed if started) and evaluate
    it on val."""
    run_dir = local_path(budget_dir(budget) / "runs" / f"{row}-{setting}")
    cfg = get_config(row, scenes_dir=str(build_setting(setting)), seed=SEED,
                     total_env_steps=budget, dropout=0.0, run_dir=str(run_dir))
    work_recorded(run_dir, lambda resumed: api.train(cfg, resume=resumed),
                  lambda resumed: "resumed and finished" if resumed else "trained")
    api.evaluate_run(run_dir, "val", out=run_dir / "val_results.json", progress=True)
    record_provenance(run_dir, "evaluated on val")
    return run_dir


def run_random(setting: str) -> Path:
    """The random policy on the setting's val episodes (it reads no perception: one run
    serves every setting with the same episodes)."""
    out = OUT / "runs" / random_name(setting)
    out.mkdir(parents=True, exist_ok=True)
    api.evaluate_policy("random", "val", scenes_dir=str(build_setting(setting)),
                        seed=SEED, out=out / "val_results.json", progress=True)
    record_provenance(out, "evaluated on val")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true",
                    help="recompute calibration.md; exit 1 if it differs")
    ap.add_argument("--budget", type=positive_int, default=BUDGET, metavar="ENV_STEPS",
                    help=f"the runs' budget (default {BUDGET:,}: the tables'); another "
                         "budget has its own folder, OUT/at_ENV_STEPS")
    sub = ap.add_subparsers(dest="command")
    r = sub.add_parser("run", help="train and val-evaluate one row on one setting")
    r.add_argument("--setting", required=True, choices=sorted(SETTINGS))
    r.add_argument("--row", required=True, choices=("we", "baseline"))
    rr = sub.add_parser("random", help="evaluate the random policy on val")
    rr.add_argument("--setting", default=next(iter(SETTINGS)), choices=sorted(SETTINGS),
                    help="whose episodes (default: the first setting's, `small`'s)")
    sub.add_parser("table", help="write calibration.md")
    args = ap.parse_args(argv)
    out = budget_dir(args.budget)
    page = lambda: table_text(out, args.budget, OUT / "runs")
    if args.check:
        return pages.regenerate({out / "calibration.md": page()}, check=True)
    if args.command is None:
        ap.error("give a command (run, random, table) or --check")
    process_provenance()                   # at start: the code this process loaded
    if args.command == "run":
        run(args.setting, args.row, args.budget)
    elif args.command == "random":
        run_random(args.setting)
    text = page()
    pages.write_pages({out / "calibration.md": text})
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
