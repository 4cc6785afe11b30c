"""Checks shared by the offline reader, importer and episode loader.

Every user-caused problem raises OfflineFormatError (a ValueError) naming the file, the
field or state key at fault and what was expected; nothing here lets a KeyError out.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from orgnav_jax.constants import (
    CATEGORY_INDEX, FLOORPLAN_OFFSET, HORIZONS, NUM_HEADINGS, ROOM_TYPE_INDEX, ROTATION_STEP,
    SPLIT_INDEX,
)
from orgnav_jax.scenes.sceneset.keys import parse_state_key, state_key

SCENE_NAME = re.compile(r"^FloorPlan(\d+)(_physics)?$")
EXAMPLES = 3  # offending items quoted in a message


class OfflineFormatError(ValueError):
    """Offline data that does not follow the authors' format (message names the file)."""


def examples(items) -> str:
    """A short quoted list: "'a', 'b', 'c' (and 7 more)"."""
    items = sorted(items, key=str)
    text = ", ".join(repr(i) for i in items[:EXAMPLES])
    return text + (f" (and {len(items) - EXAMPLES} more)" if len(items) > EXAMPLES else "")


def require_file(path: Path, what: str) -> Path:
    """`path` if it is a file; otherwise an error saying what it should hold."""
    if not path.is_file():
        raise OfflineFormatError(f"{path}: missing file ({what})")
    return path


def load_json(path: Path, what: str):
    """Parsed JSON of a required file; clear errors for a missing or broken file."""
    require_file(path, what)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise OfflineFormatError(f"{path}: not valid JSON ({e}); expected {what}") from None
    except RecursionError:
        raise OfflineFormatError(f"{path}: JSON nested too deeply to read; expected "
                                 f"{what}") from None


def floorplan_number(name: str, source: str) -> int:
    """'FloorPlan12' (or 'FloorPlan12_physics') -> 12; error otherwise."""
    m = SCENE_NAME.match(name)
    if not m:
        raise OfflineFormatError(f"{source}: scene folder {name!r} is not named FloorPlanN "
                                 "(N the AI2-THOR number, e.g. FloorPlan1, FloorPlan201)")
    number = int(m.group(1))
    if number > 2 ** 31 - 1:          # kept in an int32 array (SceneSet.floorplan)
        raise OfflineFormatError(f"{source}: scene folder {name!r}: FloorPlan number beyond "
                                 "2,147,483,647 (an int32)")
    return number


def room_type_and_split(number: int, source: str) -> tuple[int, int]:
    """AI2-THOR FloorPlan number -> (room type index, split index): 1-30 kitchen,
    201-230 living room, 301-330 bedroom, 401-430 bathroom; within a type 1-20 train,
    odd 21-29 val, even 22-30 test."""
    for name, offset in FLOORPLAN_OFFSET.items():
        k = number - offset
        if 1 <= k <= 30:
            split = "train" if k <= 20 else ("val" if k % 2 else "test")
            return ROOM_TYPE_INDEX[name], SPLIT_INDEX[split]
    raise OfflineFormatError(f"{source}: FloorPlan{number} is not an AI2-THOR room number "
                             "(expected 1-30, 201-230, 301-330 or 401-430)")


def parse_keys(keys: list, source: str) -> np.ndarray:
    """State keys "x|z|rotation|horizon" -> (S, 4) float64 poses.

    Keys must be canonical (two decimals for x and z, as the authors write them), with
    rotation a multiple of 45 in 0..315 and horizon 0 or 30.
    """
    out = np.empty((len(keys), 4), np.float64)
    for i, key in enumerate(keys):
        if not isinstance(key, str):
            raise OfflineFormatError(f"{source}: state key {key!r} is not a string")
        try:
            pose = parse_state_key(key)
        except ValueError as e:
            raise OfflineFormatError(f"{source}: {e}") from None
        rot, hor = pose[2:]
        if rot % ROTATION_STEP or not 0 <= rot < ROTATION_STEP * NUM_HEADINGS:
            raise OfflineFormatError(f"{source}: state key {key!r} has rotation {rot}, "
                                     "expected one of 0, 45, ..., 315")
        if hor not in HORIZONS:
            raise OfflineFormatError(f"{source}: state key {key!r} has horizon {hor}, "
                                     f"expected one of {list(HORIZONS)}")
        if state_key(np.float32(pose)) != key:
            raise OfflineFormatError(
                f"{source}: state key {key!r} is not in canonical form "
                f"{state_key(np.float32(pose))!r} (two decimals for x and z, whole degrees)")
        out[i] = pose
    return out


def object_type(object_id, source: str) -> str:
    """'Laptop|+01.45|+00.98|-01.89' -> 'Laptop' ('Sink|...|SinkBasin' -> 'Sink')."""
    if not isinstance(object_id, str) or "|" not in object_id or not object_id.split("|")[0]:
        raise OfflineFormatError(f"{source}: malformed objectId {object_id!r}: expected "
                                 "'Type|+x.xx|+y.yy|+z.zz', e.g. 'Laptop|+01.45|+00.98|-01.89'")
    return object_id.split("|")[0]


def check_type(name: str, source: str, unknown_types: str, ignored: set) -> int | None:
    """Category index of an object type; for a type outside the 22, an error
    (unknown_types='error') or None and the name added to `ignored` ('ignore')."""
    if name in CATEGORY_INDEX:
        return CATEGORY_INDEX[name]
    if unknown_types == "error":
        raise OfflineFormatError(f"{source}: object type {name!r} is not one of the 22 "
                                 f"categories {list(CATEGORY_INDEX)}")
    ignored.add(name)
    return None


def check_same_keys(name_a: str, keys_a, name_b: str, keys_b) -> None:
    """Both files must hold exactly the same state keys; names the first differences."""
    a, b = set(keys_a), set(keys_b)
    if a == b:
        return
    only_a, only_b = a - b, b - a
    parts = []
    if only_a:
        parts.append(f"{len(only_a)} state key(s) in {name_a} but not in {name_b}: "
                     f"{examples(only_a)}")
    if only_b:
        parts.append(f"{len(only_b)} state key(s) in {name_b} but not in {name_a}: "
                     f"{examples(only_b)}")
    raise OfflineFormatError("; ".join(parts))
