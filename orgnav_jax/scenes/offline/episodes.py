"""Evaluation episodes in the authors' form, from/to JSON and their pickle files.

A record is {"scene": "FloorPlan22", "goal_object_type": "Microwave",
"task_data": [objectIds of that type], "state": "1.25|2.00|90|30"}. Pickles are read
by PlainUnpickler, which refuses every class (so no code can run): only plain dicts,
lists, tuples, strings and numbers load. Records map onto a SceneSet through
orgnav_jax.scenes.sceneset.episodes.from_records (unreachable targets: warned, skipped and
counted).
"""

from __future__ import annotations

import io
import json
import os
import pickle
from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES
from orgnav_jax.scenes.sceneset.episodes import EpisodeSet, from_records
from orgnav_jax.scenes.sceneset.keys import state_key
from orgnav_jax.scenes.offline.exporter import object_ids
from orgnav_jax.scenes.offline.validate import OfflineFormatError, object_type
from orgnav_jax.scenes.sceneset.sceneset import SceneSet

PICKLE_SUFFIXES = (".pkl", ".pickle", ".p")


class PlainUnpickler(pickle.Unpickler):
    """Unpickler for plain data: any pickle that names a class or function is refused."""

    def find_class(self, module, name):
        raise pickle.UnpicklingError(
            f"the pickle needs {module}.{name}; only plain dicts, lists, strings and numbers "
            "are accepted (classes are refused so that loading runs no code)")

    def persistent_load(self, pid):
        raise pickle.UnpicklingError("the pickle uses persistent ids; only plain data is "
                                     "accepted")


def plain_pickle_loads(data: bytes, source: str = "pickle"):
    """Unpickle plain data only (PlainUnpickler); OfflineFormatError otherwise."""
    try:
        return PlainUnpickler(io.BytesIO(data)).load()
    except Exception as e:  # noqa: BLE001 -- untrusted bytes: any failure is a format error
        raise OfflineFormatError(f"{source}: cannot read the pickle: {e}") from None


def read_records(path: str | os.PathLike) -> list[dict]:
    """Episode records from a JSON file (a list, or {"episodes": [...]}) or a pickle."""
    path = Path(path)
    if not path.is_file():
        raise OfflineFormatError(f"{path}: episode file does not exist")
    data = path.read_bytes()
    if path.suffix in PICKLE_SUFFIXES or data[:1] == b"\x80":
        doc = plain_pickle_loads(data, str(path))
    else:
        try:
            doc = json.loads(data)
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise OfflineFormatError(
                f"{path}: not valid JSON ({e}); expected a list of episodes "
                "{scene, goal_object_type, task_data, state}") from None
        except RecursionError:
            raise OfflineFormatError(
                f"{path}: JSON nested too deeply to read; expected a list of episodes "
                "{scene, goal_object_type, task_data, state}") from None
    if isinstance(doc, dict) and isinstance(doc.get("episodes"), list):
        doc = doc["episodes"]
    if not isinstance(doc, (list, tuple)):
        raise OfflineFormatError(f"{path}: expected a list of episodes {{scene, "
                                 f"goal_object_type, task_data, state}}, got {type(doc).__name__}")
    return list(doc)


def check_task_data(records: list, source: str) -> None:
    """task_data, where given, must list objectIds of the goal type."""
    for e, rec in enumerate(records):
        if not isinstance(rec, dict) or "task_data" not in rec:
            continue  # from_records names a non-dict record
        ids = rec["task_data"]
        if not isinstance(ids, (list, tuple)):
            raise OfflineFormatError(f"{source}: episode {e} task_data is "
                                     f"{type(ids).__name__}, expected a list of objectIds")
        for oid in ids:
            t = object_type(oid, f"{source}: episode {e} task_data")
            if t != rec.get("goal_object_type"):
                raise OfflineFormatError(
                    f"{source}: episode {e} task_data objectId {oid!r} is a {t}, but "
                    f"goal_object_type is {rec.get('goal_object_type')!r}")


def load_offline_episodes(path: str | os.PathLike, scenes: SceneSet,
                          on_unreachable: str = "skip", split: str = "", seed: int = 0
                          ) -> tuple[EpisodeSet, int]:
    """Authors'-form episodes (JSON or pickle) on `scenes` -> (EpisodeSet, skipped)."""
    records = read_records(path)
    check_task_data(records, str(path))
    try:
        return from_records(records, scenes, source=str(path), on_unreachable=on_unreachable,
                            split=split, seed=seed)
    except ValueError as e:
        raise OfflineFormatError(str(e)) from None


def to_offline_records(episodes: EpisodeSet, scenes: SceneSet) -> list[dict]:
    """Episodes as authors' records; task_data holds the exporter's synthetic objectId of
    the target category (exporter.object_ids), so they match an exported scene."""
    names, pose = scenes.scene_names, np.asarray(scenes.pose)
    visible, present = np.asarray(scenes.visible), np.asarray(scenes.present)
    ids = {}
    out = []
    for n, s, c in zip(episodes.scene, episodes.start, episodes.target):
        n, s, c = int(n), int(s), int(c)          # s: the room's local state index
        rows = scenes.state_slice(n)
        if n not in ids:
            ids[n] = object_ids(pose[rows], visible[rows], present[n])
        out.append({"scene": names[n], "goal_object_type": CATEGORIES[c],
                    "task_data": [ids[n][c]], "state": state_key(pose[rows.start + s])})
    return out


def write_offline_episodes(path: str | os.PathLike, episodes: EpisodeSet, scenes: SceneSet
                           ) -> Path:
    """Write authors'-form records: a pickle (protocol 2, readable by the release) when
    the suffix is .pkl/.pickle/.p, JSON otherwise."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    records = to_offline_records(episodes, scenes)
    tmp = path.with_name(path.name + ".tmp")
    if path.suffix in PICKLE_SUFFIXES:
        tmp.write_bytes(pickle.dumps(records, protocol=2))
    else:
        tmp.write_text("[\n" + ",\n".join(json.dumps(r) for r in records) + "\n]\n")
    os.replace(tmp, path)
    return path
