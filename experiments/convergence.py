"""When rows stop learning: the convergence rule (orgnav_jax/tables/convergence.py) on
runs' val curves, and the budget campaign's page.

    python experiments/convergence.py run ROW               # train (or resume) a row to the rule
    python experiments/convergence.py check RUN_DIR...     # the rule per row (RUN-s<seed>)
    python experiments/convergence.py report               # writes the campaign's page
    python experiments/convergence.py report --check       # recompute it; exit 1 on a difference

`run ROW` trains the campaign's row ROW (ROWS: a preset and its setting) with seeds 100
and 101 in one program on the calibrated preset, 1,000-episode val evaluations, until the
rule says converged (cap 60 M env steps), in experiments/results/convergence/runs/ROW-sS;
run again, it resumes. Each process appends a provenance record to both runs (what it did,
and why it stopped: converged, the cap, or interrupted at env step N).

`check` groups run directories into rows by their name without -s<seed> and prints, per
row, the rule at its last shared evaluation and the first evaluation where it held (the
row's budget B). `report` writes experiments/results/convergence/report.md from the
committed files of the campaign's runs (experiments/results/convergence/runs/) and of the
5 M calibrated table (its rows' val curves by tenth of the budget), and the learning-curve
figure docs/figures/convergence.png (not compared by --check).
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from orgnav_jax import api
from orgnav_jax.errors import run_cli
from orgnav_jax.plots.curves import plot_curves
from orgnav_jax.tables.convergence_page import campaign_rows, report, rows_of, verdict_lines
from orgnav_jax.tables.layout import local_path
from orgnav_jax.tables.pages import regenerate
from orgnav_jax.tables.provenance import process_provenance, record_provenance
from orgnav_jax.training.config import get_config
from orgnav_jax.training.run_dir import is_run_dir, read_metrics, seed_run_dir

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "results" / "convergence"
FIGURE = ROOT / "docs" / "figures" / "convergence.png"
TABLE_5M = ROOT / "experiments" / "results" / "table_calibrated"
SEEDS = [100, 101]
CAP = 60_000_000                     # env steps: the cap of issue 65
# the campaign's rows: the preset, and what differs from its setting
ROWS = {"baseline": ("baseline", {}),
        "baseline_16envs": ("baseline", {"num_envs": 16, "updates_per_chunk": 100}),
        "we": ("we", {}),
        "org_il": ("org_il", {})}


def row_config(row: str, out: Path = OUT):
    """The campaign row's TrainConfig and whether its runs exist (then it resumes them
    with their saved config, the cap as budget)."""
    base = local_path(out / "runs" / row)
    if is_run_dir(seed_run_dir(str(base), SEEDS[0])):
        return api.resume_config(base, SEEDS, total_env_steps=CAP), True
    preset, setting = ROWS[row]
    return get_config(preset, run_dir=str(base), scene_preset="calibrated",
                      eval_episodes_per_room_type=250, total_env_steps=CAP,
                      **setting), False


def interrupted_at(run: Path) -> str:
    """What an interrupted process did to a run: the last env step its metrics record."""
    steps = max((r["env_steps"] for r in read_metrics(run, skip_broken=True)), default=0)
    return f"interrupted at about {steps:,} env steps"


def run_row(row: str, out: Path = OUT, progress: bool = True) -> str:
    """Train or resume the campaign's row until the rule says converged (or the cap), and
    append what this process did to both runs' provenance.json, also when interrupted
    (Ctrl-C, SIGTERM) -> that line."""
    cfg, resumed = row_config(row, out)
    process_provenance()                        # the code this process loaded
    did = None                                  # stays None when interrupted
    try:
        stopped = api.train_seeds(cfg, SEEDS, resume=resumed, progress=progress,
                                  until_converged=True)[0]["stopped"]
        did = f"stopped by the rule: {stopped}" if stopped else f"reached the cap ({CAP:,})"
    finally:
        for s in SEEDS:
            run = Path(seed_run_dir(cfg.run_dir, s))
            if is_run_dir(run):
                record_provenance(run, f"{'resumed' if resumed else 'trained'} in one "
                                  f"program with seeds {SEEDS[0]} {SEEDS[1]} until converged "
                                  f"(python experiments/convergence.py run {row}): "
                                  f"{did or interrupted_at(run)}")
    return did


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python experiments/convergence.py",
                                 description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="train or resume a campaign row until it converges")
    run.add_argument("row", choices=sorted(ROWS))
    run.add_argument("--quiet", action="store_true", help="no progress bar")
    chk = sub.add_parser("check", help="the rule on rows of run directories")
    chk.add_argument("run_dirs", nargs="+")
    rep = sub.add_parser("report", help="write (or --check) the campaign's page")
    rep.add_argument("--check", action="store_true")
    args = ap.parse_args(argv)
    if args.command == "run":
        # SIGTERM (a scheduler's stop) ends like Ctrl-C: the provenance records are written
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
        print(run_row(args.row, progress=not args.quiet))
        return 0
    if args.command == "check":
        for line in verdict_lines(rows_of(args.run_dirs)):
            print(line)
        return 0
    status = regenerate({OUT / "report.md": report(OUT, TABLE_5M, ROOT)}, args.check)
    rows = campaign_rows(OUT)
    if not args.check and rows:
        plot_curves(rows, FIGURE, metrics=("success",), quiet=True)
        print(f"wrote {OUT / 'report.md'} and {FIGURE}")
    return status


if __name__ == "__main__":
    sys.exit(run_cli(main))
