"""Custom splits at import: `scenes import --splits FILE.json` (see docs/offline.md).

Without a splits file a room's type and split come from its FloorPlan number (the
authors' numbering, validate.room_type_and_split). With one, FILE is a JSON object that
maps each room (scene folder name) to

    "val"                                       # FloorPlanN rooms: type from N
    {"split": "val", "room_type": "kitchen"}    # any name; room_type required unless
                                                #   the name is FloorPlanN (then it
                                                #   overrides the numbering's type)

Splits: train, val, test. Room types: kitchen, living_room, bedroom, bathroom (also
written Kitchen, LivingRoom, living room, ...). Every imported folder must be named
(only_listed=True imports just the rooms the file names), every named room must exist,
and no room may be named twice.

Scene folders: with a splits file, any subfolder holding graph.json is a room (so other
simulators' room names work), besides FloorPlanN folders. Rooms not named FloorPlanN get
scene_id 1001, 1002, ... (above every FloorPlan number present) in name order; their
names are kept in the SceneSet's info ("room_names", "room_name_ids") and
SceneSet.scene_names prints them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from orgnav_jax.constants import ROOM_TYPE_INDEX, ROOM_TYPES, SPLIT_INDEX, SPLITS
from orgnav_jax.scenes.offline import files
from orgnav_jax.scenes.offline.validate import (
    SCENE_NAME, OfflineFormatError, examples, floorplan_number, room_type_and_split,
)

CUSTOM_ID_BASE = 1000  # custom-named rooms get ids above this and above every FloorPlanN
_TYPE_ALIASES = {name.replace("_", ""): name for name in ROOM_TYPES}
_KEYS = ("split", "room_type")


def _room_type(value, path: Path, room: str) -> int:
    if isinstance(value, str):
        name = _TYPE_ALIASES.get(value.lower().replace("_", "").replace(" ", ""))
        if name is not None:
            return ROOM_TYPE_INDEX[name]
    raise OfflineFormatError(f"--splits {path}: room {room!r} has room_type {value!r}, "
                             f"expected one of {list(ROOM_TYPES)}")


def _no_duplicates(path: Path):
    def hook(pairs):
        seen = set()
        for key, _ in pairs:
            if key in seen:
                raise OfflineFormatError(f"--splits {path}: room {key!r} is named twice; "
                                         "each room must have exactly one split")
            seen.add(key)
        return dict(pairs)
    return hook


def read_splits(path: str | os.PathLike) -> dict[str, tuple[int, int | None]]:
    """FILE -> {room name: (split index, room type index or None)}; one-line errors
    (OfflineFormatError, a ValueError) naming the file and the room."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise OfflineFormatError(f"--splits {path}: cannot read the file ({e})") from None
    try:
        doc = json.loads(text, object_pairs_hook=_no_duplicates(path))
    except json.JSONDecodeError as e:
        raise OfflineFormatError(f"--splits {path}: not valid JSON ({e}); expected an "
                                 "object {room name: split}") from None
    except RecursionError:
        raise OfflineFormatError(f"--splits {path}: JSON nested too deeply; expected an "
                                 "object {room name: split}") from None
    if not isinstance(doc, dict):
        raise OfflineFormatError(f"--splits {path}: holds a JSON {type(doc).__name__}, "
                                 "expected an object {room name: 'train' | 'val' | 'test' or "
                                 "{'split': ..., 'room_type': ...}}")
    if not doc:
        raise OfflineFormatError(f"--splits {path}: names no rooms")
    out = {}
    for room, value in doc.items():
        room_type = None
        if isinstance(value, dict):
            extra = sorted(set(value) - set(_KEYS))
            if extra or "split" not in value:
                raise OfflineFormatError(
                    f"--splits {path}: room {room!r} maps to {value!r}, expected "
                    "{'split': 'train' | 'val' | 'test', 'room_type': ...} (room_type "
                    "optional for FloorPlanN names)")
            if "room_type" in value:
                room_type = _room_type(value["room_type"], path, room)
            split = value["split"]
        else:
            split = value
        if not isinstance(split, str) or split not in SPLIT_INDEX:
            raise OfflineFormatError(f"--splits {path}: room {room!r} has split {split!r}, "
                                     f"expected one of {list(SPLITS)}")
        if room_type is None and not SCENE_NAME.match(room):
            raise OfflineFormatError(
                f"--splits {path}: room {room!r} is not named FloorPlanN, so its room type "
                f"must be given: {{\"split\": \"{split}\", \"room_type\": ...}} with one of "
                f"{list(ROOM_TYPES)}")
        out[room] = (SPLIT_INDEX[split], room_type)
    return out


def room_folders(root: Path) -> dict[str, Path]:
    """Every room folder under `root` (FloorPlanN or holding graph.json), or `root`
    itself when it is one room."""
    if (root / files.GRAPH_FILE).is_file():
        return {root.name: root}
    return {p.name: p for p in root.iterdir() if p.is_dir()
            and (SCENE_NAME.match(p.name) or (p / files.GRAPH_FILE).is_file())}


def assign_splits(offline_dir: str | os.PathLike, splits_file: str | os.PathLike,
                  scenes=None, only_listed: bool = False
                  ) -> tuple[list[Path], dict[str, tuple[int, int, int]], dict[int, str]]:
    """The room folders to import and, per folder name, (scene_id, room type, split);
    and {scene_id: name} of rooms not named FloorPlanN.

    scenes: only these folder names (each must be named by the file); only_listed: the
    rooms the file names (default: every room folder, each of which it must name)."""
    root, path = Path(offline_dir), Path(splits_file)
    if not root.is_dir():
        raise OfflineFormatError(f"{root}: offline data directory does not exist")
    table = read_splits(path)
    found = room_folders(root)
    missing = [n for n in table if n not in found]
    if missing:
        raise OfflineFormatError(f"--splits {path} names room(s) {examples(missing)} that are "
                                 f"not scene folders of {root} (found {len(found)}: "
                                 f"{examples(found)})")
    if scenes:
        absent = [n for n in scenes if n not in found]
        if absent:
            raise OfflineFormatError(f"{root}: no scene folder(s) {examples(absent)} "
                                     f"(found {len(found)}: {examples(found)})")
        names = list(scenes)
    else:
        names = sorted(table) if only_listed else sorted(found)
    unnamed = [n for n in names if n not in table]
    if unnamed:
        raise OfflineFormatError(
            f"--splits {path} does not name room(s) {examples(unnamed)} of {root}: give "
            "each a split, or import only the rooms it names (--only-listed / --scenes)")
    numbers = {n: floorplan_number(n, str(path)) for n in names if SCENE_NAME.match(n)}
    next_id = max([CUSTOM_ID_BASE, *numbers.values()]) + 1
    out, custom = {}, {}
    for name in sorted(names):
        split, room_type = table[name]
        if name in numbers:
            number = numbers[name]
            if room_type is None:
                try:
                    room_type = room_type_and_split(number, f"--splits {path}")[0]
                except OfflineFormatError as e:
                    raise OfflineFormatError(f"{e}; give room {name!r} a room_type: "
                                             "{\"split\": ..., \"room_type\": ...}") from None
        else:
            number, next_id = next_id, next_id + 1
            custom[number] = name
        out[name] = (number, room_type, split)
    return [found[n] for n in names], out, custom
