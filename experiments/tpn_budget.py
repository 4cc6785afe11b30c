"""The TPN's stage-2 budget on val (issue 24): does a larger budget make the TPN help?

    python experiments/tpn_budget.py --out experiments/results/before_parity/tpn_budget \\
        --bases baseline org_il --seed 100 --budgets 40000 400000 --lrs 1e-4 1e-3 1e-2
    python experiments/tpn_budget.py --out experiments/results/before_parity/tpn_budget --check

The committed sweep was made before network parity (issue 39) and is kept in
experiments/results/before_parity/tpn_budget (the default OUT;
docs/history/why-gains-small.md); a sweep on the current networks takes an --out of its own.

For each base row: its navigation run (5 M env steps, dropout 0: the table's config) in
OUT/runs/<base>-s<seed>; for each budget a TPN trained on it for that many stage-2
episodes in OUT/runs/<base>-s<seed>/tpn-<budget>; every TPN evaluated on the val split
at each test-time learning rate (and the base alone once), on the same val episodes.
The test split is never touched. Everything resumes: rerun the same command after an
interruption (finished runs and evaluations are skipped).

OUT/budget.json holds the summary and OUT/budget.md the table (`--check` recomputes
both from the run files, which are committed: config, metrics and val results, each
results JSON checked against its per-episode outcomes by claims.read_results):
per base and budget, the stage-2 val cross-entropy and accuracy, val success at each lr,
the lr chosen on val, and its gain over the base alone with a 95% interval paired by val
episode (normal approximation; the lr was chosen on the same episodes, so the interval of
the chosen lr is optimistic).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import claims  # noqa: E402  (sibling script: results JSONs read and checked)
import run_table  # noqa: E402  (provenance records)

from orgnav_jax import api  # noqa: E402
from orgnav_jax.errors import read_json, read_object, run_cli  # noqa: E402
from orgnav_jax.training.config import get_config  # noqa: E402
from orgnav_jax.training.run_dir import is_run_dir, read_metrics  # noqa: E402


def evaluate_once(run_dir: Path, out: Path, **test_time) -> None:
    """run_dir's val results written to `out`, unless they are there already."""
    if not out.exists():
        api.evaluate_run(run_dir, "val", out=out, progress=False, **test_time)
        run_table.record_provenance(run_dir, f"evaluated on val -> {out.name}")


def paired_gain(a: dict, b: dict) -> tuple[float, float, float]:
    """Success of a minus b in points over the same episodes (per-episode arrays, as
    claims.read_results gives) -> (mean, low, high): a normal 95% interval."""
    d = 100 * (a["success"].astype(float) - b["success"])
    half = 1.96 * d.std(ddof=1) / np.sqrt(len(d))
    return d.mean(), d.mean() - half, d.mean() + half


def run_base(base: str, seed: int, out: Path, overrides: dict) -> Path:
    run_dir = out / "runs" / f"{base}-s{seed}"
    if (run_dir / "val_results.json").exists():           # finished and evaluated
        return run_dir
    cfg = get_config(base, **{**overrides, "seed": seed, "run_dir": str(run_dir)})
    resumed = is_run_dir(run_dir)
    api.train(cfg, resume=resumed, progress=sys.stderr.isatty())
    run_table.record_provenance(run_dir, "resumed and finished" if resumed else "trained")
    return run_dir


def run_tpn(base_dir: Path, budget: int, seed: int) -> Path:
    from orgnav_jax.tpn.config import get_tpn_config
    tpn_dir = base_dir / f"tpn-{budget}"
    if any(tpn_dir.glob("val_tpn@*.json")):               # finished and evaluated
        return tpn_dir
    cfg = get_tpn_config(base_dir=str(base_dir), run_dir=str(tpn_dir), seed=seed,
                         total_episodes=budget)
    resumed = is_run_dir(tpn_dir)
    api.train_tpn(cfg, resume=resumed, progress=sys.stderr.isatty())
    run_table.record_provenance(tpn_dir, "finished or reloaded the TPN" if resumed
                                else "trained the TPN")
    return tpn_dir


def last_val(tpn_dir: Path) -> dict:
    val = [r for r in read_metrics(tpn_dir, "episodes") if r["kind"] == "val"]
    return val[-1] if val else {}


def table(summary: dict) -> str:
    lrs = summary["lrs"]
    head = ["base", "stage-2 episodes", "val CE", "val accuracy", "base alone"] + \
        [f"lr {lr:g}" for lr in lrs] + ["lr chosen on val", "gain [95% interval]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for base, b in summary["bases"].items():
        for budget, t in b["budgets"].items():
            cells = [base, f"{int(budget):,}", f"{t['val_ce']:.3f}",
                     f"{100 * t['val_accuracy']:.1f}", f"{100 * b['alone']:.1f}"] + \
                [f"{100 * t['success'][f'{lr:g}']:.1f}" for lr in lrs] + \
                [f"{t['chosen']:g}", "{:+.1f} [{:+.1f}, {:+.1f}]".format(*t["gain"])]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def budget_entry(base_dir: Path, budget: int, lrs, alone: dict) -> dict:
    """One (base, budget) cell of the summary, from the TPN run's files (`alone`: the
    base's per-episode val arrays)."""
    tpn_dir = base_dir / f"tpn-{budget}"
    res = {f"{lr:g}": claims.read_results(tpn_dir / f"val_tpn@{lr:g}.json") for lr in lrs}
    chosen = max(res, key=lambda k: (res[k][0]["success"], res[k][0]["spl"]))
    v = last_val(tpn_dir)
    return {"val_ce": v.get("ce", float("nan")),
            "val_accuracy": v.get("accuracy", float("nan")),
            "success": {k: overall["success"] for k, (overall, _) in res.items()},
            "spl": {k: overall["spl"] for k, (overall, _) in res.items()},
            "chosen": float(chosen), "gain": list(paired_gain(res[chosen][1], alone))}


def summarize(out: Path, seed: int, lrs, done: dict[str, list[int]], config: dict) -> dict:
    """The summary of the finished (base, budgets) in `done`, read from the run files
    (every results JSON checked against its per-episode outcomes)."""
    summary = {"seed": seed, "lrs": list(lrs), "config": config, "bases": {}}
    for base, budgets in done.items():
        base_dir = out / "runs" / f"{base}-s{seed}"
        overall, alone = claims.read_results(base_dir / "val_results.json")
        summary["bases"][base] = {"alone": overall["success"], "budgets": {
            str(b): budget_entry(base_dir, b, lrs, alone) for b in budgets}}
    return summary


def write_summary(out: Path, summary: dict) -> str:
    out.mkdir(parents=True, exist_ok=True)
    (out / "budget.json").write_text(json.dumps(summary, indent=1))
    text = table(summary)
    (out / "budget.md").write_text(text)
    return text


def check(out: Path) -> int:
    """Recompute budget.json and budget.md from the run files; 1 on a difference."""
    path = out / "budget.json"
    doc = read_object(read_json(path, "a budget JSON"), path)
    try:
        args = (doc["seed"], doc["lrs"], {b: [int(x) for x in e["budgets"]]
                                          for b, e in doc["bases"].items()}, doc["config"])
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise ValueError(f"{path}: malformed ({type(err).__name__}: {err})") from None
    again = summarize(out, *args)
    if json.loads(json.dumps(again)) != doc or table(again) != (out / "budget.md").read_text():
        print(f"check failed: {out}/budget.json or budget.md differs from what the runs' "
              "files give", file=sys.stderr)
        return 1
    print(f"{out}: budget.json and budget.md agree with the runs' files")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path,
                    default=Path("experiments/results/before_parity/tpn_budget"))
    ap.add_argument("--bases", nargs="+", default=["baseline", "org_il"])
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--budgets", type=int, nargs="+", default=[40_000, 400_000])
    ap.add_argument("--lrs", type=float, nargs="+", default=[1e-4, 1e-3, 1e-2])
    ap.add_argument("--total-env-steps", type=int, default=5_000_000)
    ap.add_argument("--check", action="store_true",
                    help="recompute OUT's budget.json and budget.md; exit 1 on a difference")
    args = ap.parse_args(argv)
    if args.check:
        return check(args.out)
    if args.seed < 100:
        ap.error(f"--seed {args.seed}: sweeps use seeds no table uses (100+)")
    overrides = {"total_env_steps": args.total_env_steps, "dropout": 0.0}
    done: dict[str, list[int]] = {}
    for base in args.bases:
        base_dir = run_base(base, args.seed, args.out, overrides)
        evaluate_once(base_dir, base_dir / "val_results.json")
        for budget in args.budgets:
            tpn_dir = run_tpn(base_dir, budget, args.seed)
            for lr in args.lrs:
                evaluate_once(tpn_dir, tpn_dir / f"val_tpn@{lr:g}.json", tpn_lr=lr)
            done.setdefault(base, []).append(budget)
            print(write_summary(args.out, summarize(args.out, args.seed, args.lrs, done,
                                                    overrides)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2
