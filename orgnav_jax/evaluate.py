"""Evaluate a policy on a split's fixed episode set: `python -m orgnav_jax.evaluate`.

    python -m orgnav_jax.evaluate --policy random --split test
    python -m orgnav_jax.evaluate --policy expert --split val --scene-preset tiny
    python -m orgnav_jax.evaluate --episodes runs/eval/episodes-small-test.json ...
    python -m orgnav_jax.evaluate --checkpoint runs/baseline-calibrated --split test
    python -m orgnav_jax.evaluate --tpn runs/baseline-calibrated/tpn --when all   # TPN-all
    python -m orgnav_jax.evaluate --checkpoint runs/dsavn --split val --savn-act sample
    python -m orgnav_jax.evaluate --release-checkpoint model.dat --release-kind GraphModel \
        --scenes data/offline_import --split test     # the authors' trained weights

The episode set is sampled with --episode-seed (250 per room type) and written next to
the results, or replayed from --episodes. Results: a JSON file (overall, per room type,
per target; with the failure analysis: wrong_done, timeout, revisits, failed_moves, see
docs/evaluation.md) and a Table-1-style printout plus a failure table.
"""

from __future__ import annotations

import argparse
import sys

from orgnav_jax import api, evaluation
from orgnav_jax.api import is_results_json  # noqa: F401  (the results-file test)
from orgnav_jax.constants import DEFAULT_SCENE_PRESET, EPISODES_PER_ROOM_TYPE
from orgnav_jax.errors import UserError, run_cli
from orgnav_jax.safe_write import check_output_file
from orgnav_jax.tpn.config import TEST_TIME_FIELDS, add_tpn_arguments, tpn_overrides_from_args

POLICIES = ("expert", "random")


def print_results(name: str, result: dict, per_target: bool = False) -> None:
    """Table-1 metrics overall and per room type, then the failure analysis (how the
    episodes ended, revisits and failed moves per episode; docs/evaluation.md), under a
    title naming the split."""
    split = result.get("split", "?")
    print(evaluation.format_table({name: result["overall"]}, title=(
        f"{split} split, {result['overall']['episodes']} episodes"
        f"{' (unseen rooms)' if split in ('val', 'test') else ''}:")))
    print()
    print(evaluation.format_table(result["per_room_type"], title="per room type:"))
    print()
    if per_target:
        rows = {f"{t} ({m['episodes']})": m for t, m in result["per_target"].items()}
        print(evaluation.format_table(rows, title="per target category (episodes):"))
        print()
    rows = {name: result["overall"],
            **{f"  {room}": m for room, m in result["per_room_type"].items()}}
    print(evaluation.format_failures(rows, title="failure analysis (success + wrong Done + "
                                                 "timeout = 100%; moves per episode):"))


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m orgnav_jax.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    who = ap.add_mutually_exclusive_group()
    who.add_argument("--policy", choices=POLICIES, default=None)
    who.add_argument("--checkpoint", metavar="RUN_DIR", help="a training run directory")
    who.add_argument("--tpn", metavar="TPN_RUN_DIR",
                     help="a stage-2 run: its base model with TPN's test-time updates")
    who.add_argument("--release-checkpoint", metavar="FILE",
                     help="a checkpoint of the authors' release (a torch .dat state dict, "
                          "needs orgnav_jax[release], or an .npz of one); give --scenes "
                          "with its feature widths (e.g. imported offline data)")
    ap.add_argument("--release-kind", default="GraphModel",
                    choices=("BaseModel", "GraphModel", "MetaMemoryGraphModel"),
                    help="the release's model class of --release-checkpoint; "
                         "MetaMemoryGraphModel evaluates with the test-time updates of its "
                         "TPN head (the TPN options below apply; --tpn-lr 0: none)")
    ap.add_argument("--split", choices=("val", "test"), default="test")
    ap.add_argument("--scene-preset", "--preset", dest="preset", default=None,
                    help=f"scene preset (built once, cached; default {DEFAULT_SCENE_PRESET}, "
                         "with --checkpoint / --tpn the run's own; another one evaluates "
                         "the run there, with a note); --preset is the old name")
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
    ap.add_argument("--savn-act", choices=("greedy", "sample"), default=None,
                    help="a SAVN run's test-time actions (default: its config's savn_act)")
    ap.add_argument("--per-target", action="store_true",
                    help="also print success and SPL per target category")
    add_tpn_arguments(ap, TEST_TIME_FIELDS)
    return ap


def main(argv: list[str] | None = None) -> dict:
    """Parse, evaluate (api.evaluate), print the tables -> the results dict."""
    args = parser().parse_args(argv)
    if args.out is not None:     # a bad --out fails before anything loads
        if not args.out.strip():
            raise UserError("--out is empty: expected a path")
        check_output_file(args.out, is_results_json, api.RESULTS, inputs=(args.episodes,))
    loaded = api.load_policy(policy=args.policy, run_dir=args.checkpoint, tpn_dir=args.tpn,
                             release_checkpoint=args.release_checkpoint,
                             release_kind=args.release_kind, savn_act=args.savn_act,
                             **tpn_overrides_from_args(args))
    if not (args.checkpoint or args.tpn):
        loaded.scene_preset = args.preset or DEFAULT_SCENE_PRESET
    elif args.preset is not None and args.preset != api.run_scenes(loaded):
        print(f"note: {args.checkpoint or args.tpn} was trained on "
              f"{api.run_scenes(loaded, long=True)}; evaluating it on scene preset "
              f"{args.preset}, as --scene-preset asks", file=sys.stderr, flush=True)
    result = api.evaluate(loaded, args.split, scenes_dir=args.scenes, episodes=args.episodes,
                          scene_preset=args.preset,
                          episode_seed=args.episode_seed,
                          per_room_type=args.episodes_per_room_type, seed=args.seed,
                          batch_size=args.batch_size, out=args.out, progress=not args.quiet)
    print_results(loaded.policy.name, result, per_target=args.per_target)
    print(f"\nresults: {result['out']}\nepisodes: {result['episode_file']}")
    return result


if __name__ == "__main__":
    sys.exit(run_cli(main))
