"""Which actions trained agents take: mean count of each action per successful episode.

    python experiments/action_counts.py experiments/results/table_calibrated/runs/{baseline,il}-s0

For each run directory (its best-on-val checkpoint, which stays out of git: run it where
the runs were trained), the policy acts as in evaluation (greedily; a SAVN run as its
savn_act says, with its own sampling seed) on the split's seeded episode set (250 per room
type); the table has the successful episodes, their mean optimal and taken path lengths,
and the mean count of each action per successful episode.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from orgnav_jax import api, env, evaluation
from orgnav_jax.constants import ACTIONS, EPISODES_PER_ROOM_TYPE
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.errors import run_cli
from orgnav_jax.scenes.synthetic.cache import device_split


def action_counts(run_dir: str | Path, split: str = "test") -> dict:
    """A run's greedy policy on the split's seeded episodes -> {"episodes", "successes",
    "optimal", "path" (means over successful episodes), ACTION name: mean count per
    successful episode}. ValueError when no episode succeeds."""
    loaded = api.load_run(run_dir)
    scenes = device_split(loaded.scene_preset, loaded.scene_seed, loaded.scenes_dir, split)
    episodes = sample_episodes(scenes, EPISODES_PER_ROOM_TYPE, seed=0, split=split)
    trace = evaluation.trace_episodes(loaded.policy, loaded.params, scenes, episodes,
                                      env.EnvParams.evaluation())
    success = np.asarray(trace["success"]).reshape(-1).astype(bool)
    if not success.any():
        raise ValueError(f"{run_dir}: no successful {split} episode to count actions in")
    running = np.asarray(trace["running"])[success]              # (n, T) steps taken
    actions = np.asarray(trace["action"])[success]
    out = {"episodes": int(success.size), "successes": int(success.sum()),
           "optimal": float(np.asarray(episodes.optimal_len)[success].mean()),
           "path": float(np.asarray(trace["path_len"]).reshape(-1)[success].mean())}
    for a, name in enumerate(ACTIONS):
        out[name] = float(((actions == a) & running).sum(axis=1).mean())
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="training run directories (with best/)")
    ap.add_argument("--split", choices=("val", "test"), default="test")
    args = ap.parse_args(argv)
    counts = [action_counts(run, args.split) for run in args.runs]
    print("| run | successes | optimal | path | " + " | ".join(ACTIONS) + " |")
    print("|---|---|---|---|" + "---|" * len(ACTIONS))
    for run, c in zip(args.runs, counts):
        print(f"| {Path(run).name} | {c['successes']} of {c['episodes']} | "
              f"{c['optimal']:.1f} | {c['path']:.1f} | "
              + " | ".join(f"{c[a]:.2f}" for a in ACTIONS) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
