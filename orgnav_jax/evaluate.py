"""Evaluate a policy on a split's fixed episode set: `python -m orgnav_jax.evaluate`.

    python -m orgnav_jax.evaluate --policy random --split test
    python -m orgnav_jax.evaluate --policy expert --split val --preset tiny
    python -m orgnav_jax.evaluate --episodes runs/eval/episodes-small-test.json ...
    python -m orgnav_jax.evaluate --checkpoint runs/baseline-small --split test
    python -m orgnav_jax.evaluate --tpn runs/baseline-small/tpn --when all   # TPN-all

The episode set is sampled with --episode-seed (250 per room type) and written next to
the results, or replayed from --episodes. Results: a JSON file (overall, per room type,
per target; with the failure analysis: wrong_done, timeout, revisits, failed_moves, see
docs/evaluation.md) and a Table-1-style printout plus a failure table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from orgnav_jax import env, evaluation
from orgnav_jax.errors import UserError, run_cli
from orgnav_jax.episodes import (
    EPISODES_PER_ROOM_TYPE,
    is_episode_file,
    load_episodes,
    sample_episodes,
    save_episodes,
)
from orgnav_jax.safe_write import check_output_file, write_text_atomic
from orgnav_jax.scenes import SceneSet
from orgnav_jax.scenes.cache import device_split

POLICIES = {"random": evaluation.random_policy, "expert": evaluation.expert_policy}


def split_scenes(preset: str, scenes_dir: str | None, split: str, seed: int = 0) -> SceneSet:
    """One split of a saved SceneSet directory, or of the cached preset, on device: the
    set is memory-mapped and only that split's rooms are read; a process that already
    holds the split on device (training, then testing) reuses it (scenes.cache)."""
    return device_split(preset, seed, scenes_dir, split)


def episode_set(scenes: SceneSet, split: str, episodes_file: str | None, seed: int,
                per_room_type: int, default_path: Path):
    """Replay `episodes_file`, or sample a seeded set and save it at default_path."""
    if episodes_file:
        episodes = load_episodes(episodes_file, scenes)
        if len(episodes) == 0:
            raise ValueError(f"episode file {episodes_file} holds no episodes: nothing to "
                             "evaluate")
        return episodes, Path(episodes_file)
    episodes = sample_episodes(scenes, per_room_type, seed=seed, split=split)
    save_episodes(default_path, episodes, scenes)
    return episodes, default_path


def run(policy: evaluation.Policy, policy_params, scenes: SceneSet, episodes, seed: int,
        show_progress: bool = True, batch_size: int = 1000) -> dict:
    """evaluation.evaluate with a progress bar over episodes."""
    with tqdm(total=len(episodes), desc=f"evaluating {policy.name}", unit="ep",
              disable=not show_progress, file=sys.stderr) as bar:
        return evaluation.evaluate(policy, policy_params, scenes, episodes,
                                   env.EnvParams.evaluation(), seed=seed,
                                   batch_size=batch_size, progress=bar.update)


def print_results(name: str, result: dict) -> None:
    """Table-1 metrics overall and per room type, then the failure analysis (how the
    episodes ended, revisits and failed moves per episode; docs/evaluation.md)."""
    print(evaluation.format_table({name: result["overall"]}))
    print()
    print(evaluation.format_table(result["per_room_type"], title="per room type:"))
    print()
    rows = {name: result["overall"],
            **{f"  {room}": m for room, m in result["per_room_type"].items()}}
    print(evaluation.format_failures(rows, title="failure analysis (success + wrong Done + "
                                                 "timeout = 100%; moves per episode):"))


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m orgnav_jax.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    who = ap.add_mutually_exclusive_group()
    who.add_argument("--policy", choices=sorted(POLICIES), default=None)
    who.add_argument("--checkpoint", metavar="RUN_DIR", help="a training run directory")
    who.add_argument("--tpn", metavar="TPN_RUN_DIR",
                     help="a stage-2 run: its base model with TPN's test-time updates")
    ap.add_argument("--split", choices=("val", "test"), default="test")
    ap.add_argument("--preset", default="small", help="scene preset (built once, cached)")
    ap.add_argument("--scenes", metavar="DIR", help="a saved SceneSet directory instead")
    ap.add_argument("--episodes", metavar="FILE", help="replay this episode file")
    ap.add_argument("--episode-seed", type=int, default=0)
    ap.add_argument("--episodes-per-room-type", type=int, default=EPISODES_PER_ROOM_TYPE)
    ap.add_argument("--seed", type=int, default=0, help="seed of stochastic policies")
    ap.add_argument("--out", metavar="FILE", help="results JSON (default runs/eval/...)")
    ap.add_argument("--batch-size", type=int, default=None,
                    help="episodes per jitted batch (default 1000; with --tpn as many as "
                         "the per-episode fast weights allow, up to 1000)")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    from orgnav_jax.tpn.config import TEST_TIME_FIELDS, add_tpn_arguments
    add_tpn_arguments(ap, TEST_TIME_FIELDS)
    return ap


def is_results_json(path: str | Path) -> bool:
    """Whether `path` holds evaluation results this module wrote (a JSON object with
    "overall" and "per_room_type"); False for anything unreadable, binary or other."""
    try:
        with open(path, "rb") as f:
            if not f.read(64).lstrip().startswith(b"{"):
                return False
        doc = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and isinstance(doc.get("overall"), dict) \
        and isinstance(doc.get("per_room_type"), dict)


RESULTS = "an evaluation results JSON of orgnav_jax.evaluate"
EPISODE_FILE = "an episode file of orgnav_jax.evaluate"


def check_args(args: argparse.Namespace) -> None:
    """Option values and the --out file, before anything slow (UserError, FileExistsError)."""
    if args.episodes_per_room_type < 1:
        raise UserError(f"--episodes-per-room-type {args.episodes_per_room_type}: expected "
                        "an integer >= 1")
    if args.batch_size is not None and args.batch_size < 1:
        raise UserError(f"--batch-size {args.batch_size}: expected an integer >= 1")
    if args.episode_seed < 0:
        raise UserError(f"--episode-seed {args.episode_seed}: expected an integer >= 0")
    if args.out:
        check_output_file(args.out, is_results_json, RESULTS)


def main(argv: list[str] | None = None) -> dict:
    args = parser().parse_args(argv)
    check_args(args)
    preset, scenes_dir, scene_seed = args.preset, args.scenes, 0
    batch_size = args.batch_size
    from orgnav_jax.tpn.config import tpn_overrides_from_args
    if tpn_overrides_from_args(args) and not args.tpn:
        from orgnav_jax.tpn.config import TEST_TIME_FIELDS
        options = ", ".join("--" + f.replace("_", "-") for f in TEST_TIME_FIELDS)
        raise UserError(f"test-time TPN options ({options}) need --tpn TPN_RUN_DIR")
    if args.tpn:
        from orgnav_jax.tpn.policy import default_batch_size, load_tpn_policy
        policy, policy_params, run_cfg, tpn_cfg = load_tpn_policy(
            args.tpn, **tpn_overrides_from_args(args))
        preset, scenes_dir = run_cfg.scene_preset, args.scenes or run_cfg.scenes_dir
        scene_seed = run_cfg.scene_seed
        name = f"{Path(tpn_cfg.base_dir).name}-{policy.name}"
        batch_size = batch_size or default_batch_size(policy_params["base"], tpn_cfg)
    elif args.checkpoint:
        from orgnav_jax.training.policy import load_run_policy  # the trainer's checkpoints
        policy, policy_params, run_cfg = load_run_policy(args.checkpoint)
        preset, scenes_dir = run_cfg.scene_preset, args.scenes or run_cfg.scenes_dir
        scene_seed = run_cfg.scene_seed
        name = Path(args.checkpoint).name
    else:
        policy, policy_params = POLICIES[args.policy or "random"](), None
        name = args.policy or "random"
    tag = Path(scenes_dir).name if scenes_dir else preset
    out = Path(args.out or f"runs/eval/{name}-{tag}-{args.split}.json")
    check_output_file(out, is_results_json, RESULTS)
    ep_out = out.with_name(f"episodes-{tag}-{args.split}-seed{args.episode_seed}.json")
    if not args.episodes:      # a sampled set is saved beside the results
        check_output_file(ep_out, is_episode_file, EPISODE_FILE,
                          option="the episode file beside --out")
    scenes = split_scenes(preset, scenes_dir, args.split, scene_seed)
    episodes, ep_path = episode_set(
        scenes, args.split, args.episodes, args.episode_seed, args.episodes_per_room_type,
        ep_out)
    result = run(policy, policy_params, scenes, episodes, args.seed, not args.quiet,
                 batch_size or 1000)
    result.update({"policy": name, "split": args.split, "scenes": tag,
                   "episode_file": str(ep_path)})
    write_text_atomic(out, json.dumps(result, indent=1))
    print_results(policy.name, result)
    print(f"\nresults: {out}\nepisodes: {ep_path}")
    return result


if __name__ == "__main__":
    sys.exit(run_cli(main))
