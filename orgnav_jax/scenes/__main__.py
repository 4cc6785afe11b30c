"""Command line: build, inspect or render the synthetic benchmark.

    python -m orgnav_jax.scenes build --preset small --out data/small [--seed 0]
    python -m orgnav_jax.scenes build --preset large --num-rooms 10 --out data/large10
    python -m orgnav_jax.scenes build --preset small --anchor-probability 0 --out data/p0
    python -m orgnav_jax.scenes info data/small
    python -m orgnav_jax.scenes info small            # a preset's cached set (built if new)
    python -m orgnav_jax.scenes show 201 [--seed 0] [--room-sizes thor]  # ASCII top view
    python -m orgnav_jax.scenes import --offline-dir DIR --out data/thor   # authors' data
    python -m orgnav_jax.scenes export --preset tiny --out out/offline     # to their format
    python -m orgnav_jax.scenes convert OLD --out NEW [--features int8]   # format/storage
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from orgnav_jax.errors import run_cli
from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.builder import build
from orgnav_jax.scenes.sceneset import FORMAT_VERSION
from orgnav_jax.scenes.layout import ROOM_SIZE_PROFILES, generate_room, render_ascii
from orgnav_jax.scenes.offline import cli as offline_cli
from orgnav_jax.scenes.presets import SCENE_PRESETS, get_preset
from orgnav_jax.scenes.raw import build_raw_to
from orgnav_jax.scenes.storage import disk_size, is_scene_set, load, save
from orgnav_jax.scenes.summary import format_summary, summarize


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m orgnav_jax.scenes", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="generate a benchmark and save it")
    b.add_argument("--preset", default="small", help=f"one of {sorted(SCENE_PRESETS)}")
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
    b.add_argument("--json", action="store_true", help="also print the summary as JSON")
    i = sub.add_parser("info", help="summarize a saved benchmark")
    i.add_argument("path", help="a SceneSet directory, or a preset name for its cached set "
                   "($ORGNAV_CACHE or ~/.cache/orgnav_jax/scenes-PRESET-seedSEED-vFORMAT)")
    i.add_argument("--seed", type=int, default=0, help="with a preset name: its scene seed")
    i.add_argument("--json", action="store_true")
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
    offline_cli.add_parsers(sub)
    args = parser.parse_args(argv)

    if args.command in offline_cli.COMMANDS:
        return offline_cli.run(args)
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
        t0 = time.perf_counter()
        if preset.raw:  # decoded features streamed to disk (scenes/raw.py)
            scenes = build_raw_to(preset, args.seed, args.out, progress=True)
        else:
            scenes = build(preset, args.seed, progress=True)
            save(scenes, args.out)
        build_s = time.perf_counter() - t0
        summary = summarize(scenes)
        summary.update(build_s=build_s, disk_mb=disk_size(args.out) / 2**20, out=args.out)
    elif args.command == "convert":
        summary = _convert(args)
    elif args.command == "info":
        path = args.path
        if not Path(path).exists() and path in SCENE_PRESETS:
            from orgnav_jax.scenes.cache import cache_path, load_or_build
            load_or_build(path, args.seed)           # built on first use, as training does
            path = str(cache_path(path, args.seed))
            print(f"preset {args.path}, seed {args.seed}: {path}")
        elif not Path(path).exists():
            raise FileNotFoundError(f"no SceneSet at {path}: expected a SceneSet directory "
                                    f"or a preset name ({', '.join(sorted(SCENE_PRESETS))})")
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


def _convert(args) -> dict:
    import warnings

    from orgnav_jax.scenes.quantize import with_features
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


if __name__ == "__main__":
    sys.exit(run_cli(main))
