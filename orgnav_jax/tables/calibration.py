"""The perception calibration's page (calibration.md; experiments/calibration.py runs
it): per setting of the perception knobs, val success / SPL of Random, WE and the
Baseline against the targets (AI2-THOR's Table 1 values), the Baseline's release SPL and
whether its learning curve had flattened.

SETTINGS lists every setting tried, in the order tried; CHOSEN the one the `calibrated`
scene preset freezes (presets.CALIBRATED_PERCEPTION), CHOSEN_22M the one the
`calibrated_22m` preset freezes with in-view episodes (a test keeps each pair equal).
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import numpy as np

from orgnav_jax.scenes.synthetic.presets import IN_VIEW_EPISODES
from orgnav_jax.tables.runs import read_results, val_records
from orgnav_jax.training.run_dir import METRICS_FILE

SEED = 100                      # the calibration runs' seed: no table uses it
BUDGET = 5_000_000              # env steps, the tables' budget
TARGETS = {"random": (8.0, 3.0), "we": (33.0, 5.0), "baseline": (56.0, 5.0)}
TARGET_SPL = (0.32, 0.05)       # the Baseline's val SPL
FLAT_POINTS = 2.0               # the last fifth of training adds less than this

_G1 = {"global_labels": "furniture", "global_noise": 0.5, "room_style": 0.5}
_G2 = {"global_labels": "none", "global_noise": 1.0, "room_style": 1.0}
_G3 = {"global_labels": "furniture", "global_noise": 0.35, "room_style": 0.35}
_G4 = {"global_labels": "furniture", "global_noise": 0.4, "room_style": 0.4}
_G5 = {"global_labels": "furniture", "global_noise": 0.65, "room_style": 0.65}
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
_D6 = {k: round((_D1[k] + _D2[k]) / 2, 4) for k in _D1}     # halfway between d1 and d2
# setting -> perception knobs over `small` (the order they were tried)
SETTINGS: dict[str, dict] = {
    "g1": _G1, "g2": _G2, "g3": _G3,
    "g3d1": {**_G3, **_D1}, "g3d2": {**_G3, **_D2}, "g3d3": {**_G3, **_D3},
    "g4": _G4, "g4d3": {**_G4, **_D3}, "g4d1": {**_G4, **_D1}, "g4d5": {**_G4, **_D5},
    # at the converged budget (22 M env steps, issue 65 step 3): WE on g1 (-9.7 on g3 at
    # 5 M; it must lose about 10 of its converged 43.8), the Baseline on g1 with d1
    "g1d1": {**_G1, **_D1},
    # the same budget with the evaluation episodes' starts allowed to see their target
    # (suffix v: episode_distance below; it adds about 3 points to a row that mostly
    # succeeds there):
    # WE on g5 (g1 gave 37.1, -6.7 from g3), the Baseline on g5 with d2 (d2 took 10.3 from
    # d1 at 5 M)
    "g5v": _G5, "g5d2v": {**_G5, **_D2},
    # (g5d2v's val success stood at 33 at 5 M: likely below its target at 22 M)
    "g5d6v": {**_G5, **_D6},
}


# The setting the `calibrated` scene preset freezes (presets.CALIBRATED_PERCEPTION; a test
# keeps the two equal): the only setting tried whose WE and Baseline both lie inside their
# targets and whose Baseline had flattened by 5 M steps (g4d1 lies nearer both targets but
# its Baseline still gained 5 points over the last fifth of training).
CHOSEN = "g3d1"
# The setting `calibrated_22m` freezes (presets.CALIBRATED_22M_PERCEPTION with
# IN_VIEW_EPISODES), by the choice at 22 M written before its runs' results: the setting
# whose WE and Baseline both lie inside their targets on val, with Random inside its own
# on the setting's episodes; among several, the one whose Baseline lies nearest 56.
CHOSEN_22M = "g5d6v"
CHOSEN_AT = {BUDGET: CHOSEN, 22_000_000: CHOSEN_22M}   # budget -> the setting its page marks


def val_summary(run_dir: Path) -> dict | None:
    """The run's val_results.json overall figures (runs.read_results: recomputed from its
    per-episode outcomes, which it must keep), plus release_spl: SPL as the authors'
    release counts it (the start state in both path lengths: (L_opt + 1) / (max(L, L_opt)
    + 1)). None if absent."""
    path = run_dir / "val_results.json"
    if not path.exists():
        return None
    overall, per = read_results(path)
    if per is None:
        raise ValueError(f"{path}: no per-episode outcomes (the release SPL needs them)")
    ok = per["success"].astype(bool)
    L, L_opt = per["path_len"], per["optimal_len"]
    release_spl = float((ok * (L_opt + 1) / (np.maximum(L, L_opt) + 1)).mean())
    return dict(overall, release_spl=release_spl)


def curve_gain(run_dir: Path) -> float | None:
    """Val success points gained over the last fifth of training (in-training val)."""
    if not (run_dir / METRICS_FILE).exists():
        return None
    val = [(r["env_steps"], r["success"])
           for r in val_records(run_dir, need=("success",))]
    if not val:
        return None
    end = max(s for s, _ in val)
    last = [v for s, v in val if s > 0.8 * end]
    before = [v for s, v in val if 0.6 * end < s <= 0.8 * end]
    if not last or not before:
        return None
    return 100 * (float(np.mean(last)) - float(np.mean(before)))


def episode_distance(setting: str) -> dict | None:
    """The setting's ScenePreset.episode_distance: for a name ending in "v", every room
    type's evaluation episodes may start with the target in view (min 0, as the authors'
    sampler: presets.IN_VIEW_EPISODES); else None (`small`'s episodes)."""
    return IN_VIEW_EPISODES if setting.endswith("v") else None


def global_part(setting: str) -> str:
    """The setting whose knobs are this one's global-view knobs and episodes alone ("g3d1"
    -> "g3", "g5d2v" -> "g5v"): WE reads no detections, so its run on that setting serves
    every detector setting."""
    return re.sub(r"d\d+", "", setting)


def random_name(setting: str) -> str:
    """The Random run serving the setting: Random reads no perception, only episodes."""
    return "random-in-view" if episode_distance(setting) else "random"


def _cell(overall: dict | None, row: str) -> str:
    if overall is None:
        return "-"
    s, spl = 100 * overall["success"], overall["spl"]
    lo, hi = TARGETS[row][0] - TARGETS[row][1], TARGETS[row][0] + TARGETS[row][1]
    mark = " ✓" if lo <= s <= hi else ""
    return f"{s:.1f} / {spl:.3f}{mark}"


def table_text(out: Path, budget: int = BUDGET, random_runs: Path | None = None) -> str:
    """calibration.md of the calibration runs in OUT/runs, trained for `budget` env steps
    (the setting chosen at that budget, CHOSEN_AT, is marked); Random from
    random_runs/random_name(setting) (OUT/runs by default: it does not depend on the
    budget)."""
    runs = out / "runs"
    chosen = CHOSEN_AT.get(budget)
    summary = cache(val_summary)               # a run shared by several settings, read once
    lines = [
        f"# Perception calibration (val split, seed 100, {budget / 1e6:g} M env steps)",
        "",
        "Written by `python experiments/calibration.py table` from the runs' files "
        "(`--check` recomputes it). Val success (%) / SPL of the best-on-val checkpoint "
        "over the whole val split (250 episodes per room type); ✓ = inside the target. "
        "WE reads no detections: a detector setting shows the WE run of its global-view "
        "setting (g3d1: we-g3). A setting ending in v: the val episodes may start with "
        "the target in view (episode_distance min 0 for every room type; Random "
        "evaluated on those episodes). Release SPL: the Baseline's SPL counted as the authors' "
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
        we, base = summary(runs / f"we-{global_part(name)}"), summary(runs / f"baseline-{name}")
        if base is None and (we is None or global_part(name) != name):
            continue
        random = summary((random_runs or runs) / random_name(name))
        gain = curve_gain(runs / f"baseline-{name}") if base is not None else None
        spl = None if base is None else base["release_spl"]
        text = ", ".join([f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                          for k, v in knobs.items()]
                         + ["starts may see the target"] * bool(episode_distance(name)))
        lines.append(f"| {name}{' (chosen)' if name == chosen else ''} | {text} | {_cell(random, 'random')} | {_cell(we, 'we')} | "
                     f"{_cell(base, 'baseline')} | {'-' if spl is None else f'{spl:.3f}'} | "
                     f"{'-' if gain is None else f'{gain:+.1f}'} |")
    return "\n".join(lines) + "\n"
