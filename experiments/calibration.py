"""Calibrate the benchmark's perception on the rows the method does not touch (val only).

    python experiments/calibration.py run --setting g3 --row we        # one calibration run
    python experiments/calibration.py run --setting g3d1 --row baseline
    python experiments/calibration.py random                           # Random on val
    python experiments/calibration.py table                            # writes calibration.md
    python experiments/calibration.py --check                          # recompute; exit 1 if
                                                                       # calibration.md differs

A setting is a set of perception knobs (scenes/synthetic/perception.py) over the `small`
preset: the same rooms, splits, categories and episodes, only the global view and the
detector change. SETTINGS lists every setting tried, in the order tried. `run` builds the
setting's scene set once (data/calibration/<setting>, scene seed 0 as every table), trains
the row at the table's budget (5 M env steps, dropout 0, seed 100: no table uses it) in
OUT/runs/<row>-<setting>, and evaluates its best-on-val checkpoint on the whole val split
(250 episodes per room type) into val_results.json; the test split is never touched.
Random does not depend on perception: one evaluation on val (seed 100) serves every
setting.

The table (calibration.md) has, per setting, val success / SPL of Random, WE and the
Baseline beside the targets (AI2-THOR's Table 1 values: Random 8 +- 3, WE 33 +- 5, Baseline
56 +- 5, Baseline SPL 0.32 +- 0.05), and the Baseline's learning curve check: the in-training
val success gained over the last fifth of training (mean of the val evaluations in the last
fifth minus the mean of those in the fifth before; under 2 points = flattened).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run_table  # noqa: E402  (provenance records)
from orgnav_jax.errors import read_json, run_cli  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "calibration"
SEED = 100
BUDGET = 5_000_000
TARGETS = {"random": (8.0, 3.0), "we": (33.0, 5.0), "baseline": (56.0, 5.0)}
TARGET_SPL = (0.32, 0.05)       # the Baseline's val SPL
FLAT_POINTS = 2.0               # the last fifth of training adds less than this

_G1 = {"global_labels": "furniture", "global_noise": 0.5, "room_style": 0.5}
_G2 = {"global_labels": "none", "global_noise": 1.0, "room_style": 1.0}
_G3 = {"global_labels": "furniture", "global_noise": 0.35, "room_style": 0.35}
_G4 = {"global_labels": "furniture", "global_noise": 0.4, "room_style": 0.4}
_D1 = {"detect_range_scale": 0.7, "peak_recall": 0.8, "min_box_area": 64.0,
       "false_positive_rate": 0.05, "fp_confidence_max": 0.7, "confidence_noise": 0.15,
       "confusion": 0.15, "box_jitter": 5.0, "appearance_noise": 1.0}
_D2 = {"detect_range_scale": 0.5, "peak_recall": 0.7, "min_box_area": 144.0,
       "false_positive_rate": 0.1, "fp_confidence_max": 0.9, "confidence_noise": 0.2,
       "confusion": 0.3, "box_jitter": 10.0, "appearance_noise": 1.5}
_D3 = {"detect_range_scale": 0.85, "peak_recall": 0.875, "min_box_area": 32.0,
       "false_positive_rate": 0.03, "fp_confidence_max": 0.5, "confidence_noise": 0.12,
       "confusion": 0.075, "box_jitter": 2.5, "appearance_noise": 0.75}
_D5 = {k: round((_D1[k] + _D3[k]) / 2, 4) for k in _D1}     # halfway between d1 and d3
# setting -> perception knobs over `small` (the order they were tried)
SETTINGS: dict[str, dict] = {
    "g1": _G1, "g2": _G2, "g3": _G3,
    "g3d1": {**_G3, **_D1}, "g3d2": {**_G3, **_D2}, "g3d3": {**_G3, **_D3},
    "g4": _G4, "g4d3": {**_G4, **_D3}, "g4d1": {**_G4, **_D1}, "g4d5": {**_G4, **_D5},
}


# The setting the `calibrated` scene preset freezes (presets.CALIBRATED_PERCEPTION; a test
# keeps the two equal): the only setting tried whose WE and Baseline both lie inside their
# targets and whose Baseline had flattened by 5 M steps (g4d1 lies nearer both targets but
# its Baseline still gained 5 points over the last fifth of training).
CHOSEN = "g3d1"


def scenes_dir(setting: str) -> Path:
    return Path("data") / "calibration" / setting


def build_setting(setting: str) -> Path:
    """The setting's scene set (built once, reused)."""
    from orgnav_jax.scenes import build, save
    from orgnav_jax.scenes.sceneset.storage import is_scene_set
    from orgnav_jax.scenes.synthetic.perception import Perception
    path = scenes_dir(setting)
    if not is_scene_set(path):
        save(build("small", 0, perception=Perception(**SETTINGS[setting]), progress=True),
             path)
    return path


def run(setting: str, row: str) -> Path:
    """Train `row` on the setting (resumed if started) and evaluate it on val."""
    from orgnav_jax import api
    from orgnav_jax.training.config import get_config
    from orgnav_jax.training.run_dir import is_run_dir
    run_dir = OUT / "runs" / f"{row}-{setting}"
    resume = is_run_dir(run_dir)
    cfg = get_config(row, scenes_dir=str(build_setting(setting)), seed=SEED,
                     total_env_steps=BUDGET, dropout=0.0, run_dir=str(run_dir))
    api.train(cfg, resume=resume)
    run_table.record_provenance(run_dir, "resumed and finished" if resume else "trained")
    api.evaluate_run(run_dir, "val", out=run_dir / "val_results.json", progress=True)
    run_table.record_provenance(run_dir, "evaluated on val")
    return run_dir


def run_random() -> Path:
    from orgnav_jax import api
    out = OUT / "runs" / "random"
    out.mkdir(parents=True, exist_ok=True)
    api.evaluate_policy("random", "val", scenes_dir=str(build_setting(next(iter(SETTINGS)))),
                        seed=SEED, out=out / "val_results.json", progress=True)
    run_table.record_provenance(out, "evaluated on val")
    return out


def _val(run_dir: Path) -> dict | None:
    """The run's val_results.json overall figures, its success checked against the
    per-episode outcomes, plus release_spl: SPL as the authors' release counts it (the
    start state in both path lengths: (L_opt + 1) / (max(L, L_opt) + 1)). None if absent."""
    path = run_dir / "val_results.json"
    if not path.exists():
        return None
    doc = read_json(path, "a results JSON")
    overall, pe = doc["overall"], doc["per_episode"]
    ok = np.asarray(pe["outcome"]) == 0
    if abs(float(ok.mean()) - overall["success"]) > 1e-9:
        raise ValueError(f"{path}: overall success {overall['success']} differs from its "
                         f"per-episode outcomes ({float(ok.mean())})")
    L, L_opt = np.asarray(pe["path_len"]), np.asarray(pe["optimal_len"])
    release_spl = float((ok * (L_opt + 1) / (np.maximum(L, L_opt) + 1)).mean())
    return dict(overall, release_spl=release_spl)


def curve_gain(run_dir: Path) -> float | None:
    """Val success points gained over the last fifth of training (in-training val)."""
    path = run_dir / "metrics.jsonl"
    if not path.exists():
        return None
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    val = [(r["env_steps"], r["success"]) for r in rows if r.get("kind") == "val"]
    if not val:
        return None
    end = max(s for s, _ in val)
    last = [v for s, v in val if s > 0.8 * end]
    before = [v for s, v in val if 0.6 * end < s <= 0.8 * end]
    if not last or not before:
        return None
    return 100 * (float(np.mean(last)) - float(np.mean(before)))


def global_part(setting: str) -> str:
    """The setting whose knobs are this one's global-view knobs alone ("g3d1" -> "g3"):
    WE reads no detections, so its run on that setting serves every detector setting."""
    return setting.split("d")[0]


def _cell(overall: dict | None, row: str) -> str:
    if overall is None:
        return "-"
    s, spl = 100 * overall["success"], overall["spl"]
    lo, hi = TARGETS[row][0] - TARGETS[row][1], TARGETS[row][0] + TARGETS[row][1]
    mark = " ✓" if lo <= s <= hi else ""
    return f"{s:.1f} / {spl:.3f}{mark}"


def table_text(out: Path = OUT) -> str:
    runs = out / "runs"
    random = _val(runs / "random")
    lines = [
        "# Perception calibration (val split, seed 100, 5 M env steps)",
        "",
        "Written by `python experiments/calibration.py table` from the runs' files "
        "(`--check` recomputes it). Val success (%) / SPL of the best-on-val checkpoint "
        "over the whole val split (250 episodes per room type); ✓ = inside the target. "
        "WE reads no detections: a detector setting shows the WE run of its global-view "
        "setting (g3d1: we-g3). Release SPL: the Baseline's SPL counted as the authors' "
        "release counts it (start state included in both lengths), the convention of the "
        "paper's 0.32. Baseline flat: val success points gained over the last fifth of "
        "training (in-training val; < 2 = flattened).",
        "",
        f"Targets (AI2-THOR, the paper's Table 1): Random {TARGETS['random'][0]:g} ± "
        f"{TARGETS['random'][1]:g}, WE {TARGETS['we'][0]:g} ± {TARGETS['we'][1]:g}, "
        f"Baseline {TARGETS['baseline'][0]:g} ± {TARGETS['baseline'][1]:g} "
        f"(SPL {TARGET_SPL[0]:g} ± {TARGET_SPL[1]:g}).",
        "",
        "| setting | knobs over `small` | Random | WE | Baseline | release SPL | "
        "Baseline flat |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, knobs in SETTINGS.items():
        we, base = _val(runs / f"we-{global_part(name)}"), _val(runs / f"baseline-{name}")
        if base is None and (we is None or global_part(name) != name):
            continue
        gain = curve_gain(runs / f"baseline-{name}") if base is not None else None
        spl = None if base is None else base["release_spl"]
        text = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                         for k, v in knobs.items())
        lines.append(f"| {name}{' (chosen)' if name == CHOSEN else ''} | {text} | {_cell(random, 'random')} | {_cell(we, 'we')} | "
                     f"{_cell(base, 'baseline')} | {'-' if spl is None else f'{spl:.3f}'} | "
                     f"{'-' if gain is None else f'{gain:+.1f}'} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check", action="store_true",
                    help="recompute calibration.md; exit 1 if it differs")
    sub = ap.add_subparsers(dest="command")
    r = sub.add_parser("run", help="train and val-evaluate one row on one setting")
    r.add_argument("--setting", required=True, choices=sorted(SETTINGS))
    r.add_argument("--row", required=True, choices=("we", "baseline"))
    sub.add_parser("random", help="evaluate the random policy on val")
    sub.add_parser("table", help="write calibration.md")
    args = ap.parse_args(argv)
    if args.check:
        want = table_text()
        have = (OUT / "calibration.md").read_text() if (OUT / "calibration.md").exists() else ""
        if want != have:
            print(f"{OUT / 'calibration.md'} differs from what the runs give", file=sys.stderr)
            return 1
        print("calibration.md matches the runs")
        return 0
    if args.command is None:
        ap.error("give a command (run, random, table) or --check")
    run_table._STARTED.update(run_table.provenance())
    if args.command == "run":
        run(args.setting, args.row)
    elif args.command == "random":
        run_random()
    text = table_text()
    (OUT / "calibration.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
