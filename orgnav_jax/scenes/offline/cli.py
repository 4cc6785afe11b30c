"""`import` and `export` subcommands of `python -m orgnav_jax.scenes`.

    python -m orgnav_jax.scenes import --offline-dir Data/AI2thor_offline_data --out data/thor
    python -m orgnav_jax.scenes import --offline-dir DIR --out OUT --splits splits.json
    python -m orgnav_jax.scenes export --preset tiny --out out/offline [--episodes-per-type 250]
    python -m orgnav_jax.scenes export --from data/small --out out/offline
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from orgnav_jax.constants import SPLITS
from orgnav_jax.scenes.offline.validate import OfflineFormatError

COMMANDS = ("import", "export")


def add_parsers(sub) -> None:
    """Add the two subcommands to an argparse subparsers object."""
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
    from orgnav_jax.scenes.offline.importer import format_report, import_to
    from orgnav_jax.scenes.summary import format_summary, summarize
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
    import numpy as np

    from orgnav_jax.episodes import sample_episodes
    from orgnav_jax.scenes.builder import build
    from orgnav_jax.offline_episodes import write_offline_episodes
    from orgnav_jax.scenes.offline.exporter import check_export_dir, export_offline
    from orgnav_jax.scenes.storage import load
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


def run(args: argparse.Namespace) -> int:
    """Run the parsed `import` or `export` command."""
    return _import(args) if args.command == "import" else _export(args)
