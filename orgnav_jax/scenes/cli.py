"""Command line: build, inspect or render the synthetic benchmark.

    python -m orgnav_jax.scenes build --preset small --out data/small [--seed 0]
    python -m orgnav_jax.scenes build --preset large --num-rooms 10 --out data/large10
    python -m orgnav_jax.scenes build --preset small --anchor-probability 0 --out data/p0
    python -m orgnav_jax.scenes build --preset small --perception confusion=0.2 --out data/c
    python -m orgnav_jax.scenes build --preset calibrated --episode-distance bathroom=4 --out D
    python -m orgnav_jax.scenes info data/small
    python -m orgnav_jax.scenes episodes calibrated   # evaluation episodes' path lengths
    python -m orgnav_jax.scenes info small            # a preset's cached set (built if new)
    python -m orgnav_jax.scenes show 201 [--seed 0] [--room-sizes thor]  # ASCII top view
    python -m orgnav_jax.scenes import --offline-dir DIR --out data/thor   # authors' data
    python -m orgnav_jax.scenes export --preset tiny --out out/offline     # to their format
    python -m orgnav_jax.scenes convert OLD --out NEW [--features int8]   # format/storage
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import warnings
from pathlib import Path

import numpy as np

from orgnav_jax.constants import (
    DEFAULT_SCENE_PRESET, EPISODES_PER_ROOM_TYPE, ROOM_TYPES, SPLITS)
from orgnav_jax.episodes import length_stats, sample_episodes
from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.offline.episodes import write_offline_episodes
from orgnav_jax.scenes.offline.exporter import check_export_dir, export_offline
from orgnav_jax.scenes.offline.importer import format_report, import_to
from orgnav_jax.scenes.offline.validate import OfflineFormatError
from orgnav_jax.scenes.sceneset.fields import FORMAT_VERSION
from orgnav_jax.scenes.sceneset.quantize import with_features
from orgnav_jax.scenes.sceneset.storage import disk_size, is_scene_set, load, save
from orgnav_jax.scenes.summary import format_summary, summarize
from orgnav_jax.scenes.synthetic.builder import build
from orgnav_jax.scenes.synthetic.cache import cache_path, load_or_build
from orgnav_jax.scenes.synthetic.layout import ROOM_SIZE_PROFILES, generate_room, render_ascii
from orgnav_jax.scenes.synthetic.perception import parse_knobs
from orgnav_jax.scenes.synthetic.presets import (
    SCENE_PRESETS, get_preset, parse_episode_distance)
from orgnav_jax.scenes.synthetic.raw import build_raw_to


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orgnav_jax.scenes", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="generate a benchmark and save it")
    b.add_argument("--preset", default=DEFAULT_SCENE_PRESET,
                   help=f"one of {sorted(SCENE_PRESETS)} (default {DEFAULT_SCENE_PRESET})")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--out", required=True, help="output directory (an existing SceneSet is "
                   "replaced atomically; any other non-empty directory is refused)")
    b.add_argument("--rooms", nargs=3, type=int, metavar=("TRAIN", "VAL", "TEST"),
                   help="rooms per room type per split (default: the preset's)")
    b.add_argument("--num-rooms", type=int, help="only N rooms in all, taken in turn from "
                   "each room type and split (e.g. 10, 20, 40 of preset large)")
    b.add_argument("--global-dim", type=int, help="G, channels of the 7x7 global map "
                   "(default: the preset's)")
    b.add_argument("--appearance-dim", type=int, help="d, appearance feature width "
                   "(default: the preset's)")
    b.add_argument("--anchor-probability", type=float, metavar="P",
                   help="how often an object with anchors is placed by one (0: anywhere, "
                        "1: always; default 0.85, the generator's): the co-occurrence knob")
    b.add_argument("--perception", nargs="+", metavar="NAME=VALUE",
                   help="perception knobs over the preset's (docs/calibrated.md), e.g. "
                        "global_labels=none global_noise=0.5 confusion=0.2")
    b.add_argument("--episode-distance", nargs="+", metavar="ROOM=MIN[:MAX]",
                   help="bounds on the optimal path length (moves) of the evaluation "
                        "episodes per room type (docs/calibrated.md), e.g. living_room=6 "
                        "kitchen=1:18; default: any target at least one move away")
    b.add_argument("--json", action="store_true", help="also print the summary as JSON")
    i = sub.add_parser("info", help="summarize a saved benchmark")
    i.add_argument("path", help="a SceneSet directory, or a preset name for its cached set "
                   "($ORGNAV_CACHE or ~/.cache/orgnav_jax/scenes-PRESET-seedSEED-vFORMAT)")
    i.add_argument("--seed", type=int, default=0, help="with a preset name: its scene seed")
    i.add_argument("--json", action="store_true")
    ep = sub.add_parser("episodes", help="optimal path lengths of a set's seeded evaluation "
                        "episodes, per split and room type")
    ep.add_argument("path", help="a SceneSet directory, or a preset name for its cached set")
    ep.add_argument("--seed", type=int, default=0, help="with a preset name: its scene seed")
    ep.add_argument("--splits", nargs="+", choices=SPLITS, default=["val", "test"])
    ep.add_argument("--episodes-per-room-type", type=int, default=EPISODES_PER_ROOM_TYPE)
    ep.add_argument("--episode-seed", type=int, default=0,
                    help="the episode sampler's seed (0: the evaluation's default)")
    ep.add_argument("--json", action="store_true")
    s = sub.add_parser("show", help="print the ASCII top view of one generated room")
    s.add_argument("floorplan", type=int, help="AI2-THOR number, e.g. 1, 201, 301, 401")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--room-sizes", default="default", choices=sorted(ROOM_SIZE_PROFILES),
                   help="room-size profile: default, or thor (AI2-THOR's, preset large)")
    c = sub.add_parser("convert", help="rewrite a saved SceneSet in the current format "
                       "(e.g. a padded version-1 set) and/or another feature storage")
    c.add_argument("source", help="a saved SceneSet directory (any readable version)")
    c.add_argument("--out", required=True, help="output directory (may be the source: it "
                   "is replaced atomically)")
    c.add_argument("--features", choices=("float16", "int8"), help="feature storage "
                   "(default: keep): int8 stores them with a per-channel scale")
    c.add_argument("--json", action="store_true", help="also print the summary as JSON")
    _add_offline_parsers(sub)
    args = parser.parse_args(argv)
    seed = getattr(args, "seed", None)
    if seed is not None and not 0 <= seed <= 2 ** 31 - 1:   # before any build or progress bar
        raise ValueError(f"--seed {seed}: expected an integer 0 <= seed <= 2,147,483,647")

    if args.command == "import":
        return _import(args)
    if args.command == "export":
        return _export(args)
    if args.command == "build":
        if args.preset not in SCENE_PRESETS:
            parser.error(f"unknown preset {args.preset!r}: expected one of {sorted(SCENE_PRESETS)}")
        check_output_dir(args.out, is_scene_set, "a SceneSet")  # before the build
        overrides = {k: v for k, v in (("rooms_per_type", tuple(args.rooms or ()) or None),
                                       ("num_rooms", args.num_rooms),
                                       ("global_dim", args.global_dim),
                                       ("appearance_dim", args.appearance_dim),
                                       ("anchor_probability", args.anchor_probability))
                     if v is not None}
        preset = get_preset(args.preset, **overrides)
        if args.perception:
            preset = get_preset(preset, perception=dataclasses.replace(
                preset.perception, **parse_knobs(args.perception)))
        if args.episode_distance:
            bounds = dict(preset.episode_distance or ())
            bounds.update(parse_episode_distance(args.episode_distance))
            preset = get_preset(preset, episode_distance=bounds)
        t0 = time.perf_counter()
        if preset.raw:  # decoded features streamed to disk (synthetic/raw.py)
            scenes = build_raw_to(preset, args.seed, args.out, progress=True)
        else:
            scenes = build(preset, args.seed, progress=True)
            save(scenes, args.out)
        build_s = time.perf_counter() - t0
        summary = summarize(scenes)
        summary.update(build_s=build_s, disk_mb=disk_size(args.out) / 2**20, out=args.out)
    elif args.command == "convert":
        summary = _convert(args)
    elif args.command == "episodes":
        return _episodes(args)
    elif args.command == "info":
        path = _set_path(args.path, args.seed)
        summary = summarize(load(path, mmap=True))
        summary.update(disk_mb=disk_size(path) / 2**20)
    else:
        print(render_ascii(generate_room(args.seed, args.floorplan,
                                         room_sizes=args.room_sizes)))
        print("# wall, = furniture, o blocking object, . reachable, * object, D door")
        return 0
    print(format_summary(summary))
    if args.json:
        print(json.dumps(summary))
    return 0


def _set_path(path: str, seed: int) -> str:
    """A SceneSet directory, or a preset name's cached set (built on first use, as
    training does); FileNotFoundError for anything else."""
    if not Path(path).exists() and path in SCENE_PRESETS:
        load_or_build(path, seed)
        print(f"preset {path}, seed {seed}: {cache_path(path, seed)}")
        return str(cache_path(path, seed))
    if not Path(path).exists():
        raise FileNotFoundError(f"no SceneSet at {path}: expected a SceneSet directory "
                                f"or a preset name ({', '.join(sorted(SCENE_PRESETS))})")
    return path


def _episodes(args) -> int:
    """Print the optimal path lengths (mean / median, moves) of the seeded evaluation
    episodes of each split, per room type (episodes.length_stats)."""
    if args.episodes_per_room_type < 1:
        raise ValueError(f"--episodes-per-room-type {args.episodes_per_room_type}: expected "
                         "an integer >= 1")
    if args.episode_seed < 0:
        raise ValueError(f"--episode-seed {args.episode_seed}: expected an integer >= 0")
    scenes = load(_set_path(args.path, args.seed), mmap=True)
    stats = {}
    for split in args.splits:
        view = scenes.split_view(split)
        if view.num_scenes:
            stats[split] = length_stats(sample_episodes(
                view, args.episodes_per_room_type, seed=args.episode_seed, split=split))
    columns = list(ROOM_TYPES) + ["all"]
    print(f"optimal path length (moves), mean / median of {args.episodes_per_room_type} "
          f"episodes per room type, episode seed {args.episode_seed}")
    print(f"{'split':<6}" + "".join(f"{c:>14}" for c in columns))
    for split, per in stats.items():
        cells = (f"{per[c]['mean']:.2f} / {per[c]['median']:g}" if c in per else "-"
                 for c in columns)
        print(f"{split:<6}" + "".join(f"{cell:>14}" for cell in cells))
    if args.json:
        print(json.dumps(stats))
    return 0


def _convert(args) -> dict:
    check_output_dir(args.out, is_scene_set, "a SceneSet")
    with warnings.catch_warnings():      # the old-format warning names this very command
        warnings.simplefilter("ignore")
        scenes = load(args.source, mmap=True)
    scenes = with_features(scenes, args.features)
    save(scenes, args.out, validate=args.features is not None)
    summary = summarize(load(args.out, mmap=True))
    summary.update(disk_mb=disk_size(args.out) / 2**20, out=args.out)
    print(f"converted {args.source} -> {args.out} (format version {FORMAT_VERSION})")
    return summary


def _add_offline_parsers(sub) -> None:
    """The `import` and `export` subcommands (the authors' offline format)."""
    i = sub.add_parser("import", help="import the authors' offline AI2-THOR data and save it")
    i.add_argument("--offline-dir", required=True, help="folder of FloorPlanN scene folders")
    i.add_argument("--out", required=True, help="SceneSet directory (an existing SceneSet "
                   "is replaced atomically; any other non-empty directory is refused)")
    i.add_argument("--scenes", nargs="+", help="only these folders, e.g. FloorPlan1 FloorPlan2")
    i.add_argument("--splits", help="JSON object: room (folder) name -> 'train' | 'val' | "
                   "'test', or {\"split\": ..., \"room_type\": ...} (required for names other "
                   "than FloorPlanN); replaces the FloorPlan numbering (docs/offline.md)")
    i.add_argument("--only-listed", action="store_true", help="with --splits: import only "
                   "the rooms the file names (default: it must name every scene folder)")
    i.add_argument("--detection-file", help="detection hdf5 name (default: first found of "
                   "fasterrcnn_features_22cls.hdf5, det_feature_categories.hdf5, ...)")
    i.add_argument("--detection-classes", help="JSON file: list of the detection file's class "
                   "names in row order (needed when it does not have exactly 22 rows)")
    i.add_argument("--detection-rows", help="comma-separated row index of each of the 22 "
                   "categories (alternative to --detection-classes)")
    i.add_argument("--strict-types", action="store_true", help="error on object types "
                   "outside the 22 (default: ignore them and report their names)")
    i.add_argument("--ignore-unmatched-edges", action="store_true",
                   help="drop graph edges matching no action instead of failing")
    i.add_argument("--features", choices=("float16", "int8"), default="float16",
                   help="storage of the large features: float16 (default) or int8 with a "
                   "per-channel scale (half the bytes; dequantized inside jit)")
    i.add_argument("--json", action="store_true", help="also print the report as JSON")
    e = sub.add_parser("export", help="write a SceneSet in the authors' offline format")
    src = e.add_mutually_exclusive_group(required=True)
    src.add_argument("--from", dest="source", help="a saved SceneSet directory")
    src.add_argument("--preset", help="build this preset (tiny, small, paper) and export it")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--rooms", nargs=3, type=int, metavar=("TRAIN", "VAL", "TEST"),
                   help="with --preset: rooms per type per split")
    e.add_argument("--scenes", nargs="+", help="only these scenes, e.g. FloorPlan1")
    e.add_argument("--out", required=True, help="output folder (one FloorPlanN per scene; "
                   "empty or an earlier export, anything else is refused)")
    e.add_argument("--hdf5-dtype", default="float32", choices=("float32", "float16"))
    e.add_argument("--episodes-per-type", type=int, default=0, help="also write seeded "
                   "evaluation episodes per split in the authors' form (JSON and pickle)")
    e.add_argument("--json", action="store_true")


def _rows(args):
    if args.detection_classes is not None and args.detection_rows is not None:
        raise OfflineFormatError("give --detection-classes or --detection-rows, not both")
    if args.detection_classes is not None:
        path = Path(args.detection_classes)
        try:
            names = json.loads(path.read_text())
        except (OSError, ValueError) as e:  # JSONDecodeError, UnicodeDecodeError
            raise OfflineFormatError(f"--detection-classes {path}: cannot read a JSON list "
                                     f"of class names ({e})") from None
        except RecursionError:
            raise OfflineFormatError(f"--detection-classes {path}: JSON nested too deeply; "
                                     "expected a JSON list of class names") from None
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise OfflineFormatError(f"--detection-classes {path}: expected a JSON list of "
                                     "class names in row order")
        return names
    if args.detection_rows is not None:
        rows = [r.strip() for r in args.detection_rows.split(",")]
        if not all(rows):
            raise OfflineFormatError(f"--detection-rows {args.detection_rows!r}: expected "
                                     "comma-separated class names, none empty")
        return rows
    return None


def _import(args) -> int:
    if args.only_listed and not args.splits:
        raise OfflineFormatError("--only-listed needs --splits FILE.json")
    scenes, report = import_to(
        args.offline_dir, args.out, scenes=args.scenes, detection_file=args.detection_file,
        detection_rows=_rows(args), unknown_types="error" if args.strict_types else "ignore",
        unmatched_edges="ignore" if args.ignore_unmatched_edges else "error", progress=True,
        splits=args.splits, only_listed=args.only_listed, features=args.features)
    print(format_report(report))
    print(format_summary(summarize(scenes)))
    print(f"saved to {args.out}")
    if args.json:
        print(json.dumps(report))
    return 0


def _export(args) -> int:
    if args.episodes_per_type < 0:
        raise OfflineFormatError(f"--episodes-per-type {args.episodes_per_type}: expected an "
                                 "integer >= 0 (0: no episode files)")
    check_export_dir(args.out)  # before building: refuse a folder that is not ours
    if args.source:
        scenes = load(args.source, mmap=True)
    else:
        overrides = {"rooms_per_type": tuple(args.rooms)} if args.rooms else {}
        scenes = build(args.preset, args.seed, progress=True, **overrides)
    if args.scenes:
        names = scenes.scene_names
        missing = [n for n in args.scenes if n not in names]
        if missing:
            raise OfflineFormatError(f"--scenes: {missing} not in this SceneSet ({names[:4]}...)")
        scenes = scenes.select([names.index(n) for n in args.scenes])
    report = export_offline(scenes, args.out, hdf5_dtype=args.hdf5_dtype, progress=True)
    if args.episodes_per_type > 0:
        report["episodes"] = {}
        for k, split in enumerate(SPLITS):
            if not (np.asarray(scenes.split) == k).any():
                continue
            view = scenes.split_view(split)
            eps = sample_episodes(view, args.episodes_per_type, seed=args.seed, split=split)
            for suffix in (".json", ".pkl"):
                write_offline_episodes(Path(args.out) / "episodes" / f"{split}{suffix}", eps, view)
            report["episodes"][split] = len(eps)
    print(f"exported {report['scenes']} scene(s), {report['states']} states to {args.out} "
          f"({report['bytes'] / 2**20:.1f} MB) in {report['seconds']:.1f} s")
    if args.json:
        print(json.dumps(report))
    return 0
