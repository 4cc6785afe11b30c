"""Episodes over one SceneSet: the EpisodeSet data type and its authors'-form records.

An EpisodeSet indexes one SceneSet (usually a split view): episode e starts in scene
`scene[e]` at state `start[e]` (the room's LOCAL state index) looking for category
`target[e]`. A record names rooms and poses, never array indices (the authors' form):
{"scene": "FloorPlan22", "goal_object_type": "Microwave", "state": "1.25|2.00|90|30",
"optimal_len": 9}. Part of the data model, so that every scene source (the authors'
episode files: scenes/offline/episodes.py) and the episode files of orgnav_jax.episodes
(sampling, save and load) share it without a scene source importing a layer above it.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from orgnav_jax.constants import CATEGORIES, category_index
from orgnav_jax.errors import read_int, read_str
from orgnav_jax.scenes.sceneset.fields import UNREACHABLE
from orgnav_jax.scenes.sceneset.keys import key_index, state_key
from orgnav_jax.scenes.sceneset.sceneset import SceneSet


@dataclasses.dataclass(frozen=True)
class EpisodeSet:
    """E episodes over one SceneSet; every array is (E,) int32."""
    scene: np.ndarray
    start: np.ndarray
    target: np.ndarray
    optimal_len: np.ndarray
    room_type: np.ndarray
    split: str = ""
    seed: int = 0

    def __len__(self) -> int:
        return int(self.scene.shape[0])

    def subset(self, index) -> EpisodeSet:
        """The episodes at `index` (ints or a bool mask)."""
        pick = lambda a: np.asarray(a)[index]
        return dataclasses.replace(self, scene=pick(self.scene), start=pick(self.start),
                                   target=pick(self.target),
                                   optimal_len=pick(self.optimal_len),
                                   room_type=pick(self.room_type))


def to_records(episodes: EpisodeSet, scenes: SceneSet) -> list[dict]:
    """Episodes in the authors' JSON form (plus optimal_len)."""
    names = scenes.scene_names
    pose, offsets = np.asarray(scenes.pose), np.asarray(scenes.state_offset)
    return [{"scene": names[n], "goal_object_type": CATEGORIES[c],
             "state": state_key(pose[offsets[n] + s]), "optimal_len": int(L)}
            for n, s, c, L in zip(episodes.scene, episodes.start, episodes.target,
                                  episodes.optimal_len)]


def from_records(records: list[dict], scenes: SceneSet, source: str = "episodes",
                 on_unreachable: str = "error", split: str = "", seed: int = 0
                 ) -> tuple[EpisodeSet, int]:
    """Episodes from authors'-form records -> (EpisodeSet, number skipped).

    Each record needs "scene", "goal_object_type" and "state"; "optimal_len", when
    present, must match these scenes. A target not visible from anywhere reachable is an
    error, or with on_unreachable="skip" a warning and a skip (counted)."""
    if on_unreachable not in ("error", "skip"):
        raise ValueError(f"on_unreachable must be 'error' or 'skip', got {on_unreachable!r}")
    names = {name: i for i, name in enumerate(scenes.scene_names)}
    pose, counts = np.asarray(scenes.pose), np.asarray(scenes.state_count)
    offsets = np.asarray(scenes.state_offset)
    dist, targets = np.asarray(scenes.dist), np.asarray(scenes.targets)
    room_type = np.asarray(scenes.room_type)
    index_cache: dict[int, dict[str, int]] = {}
    rows, skipped = [], 0
    for e, rec in enumerate(records):
        where = f"{source}: episode {e}"
        if not isinstance(rec, dict):
            raise ValueError(f"{where} must be an object, got {type(rec).__name__}")
        missing = [k for k in ("scene", "goal_object_type", "state") if k not in rec]
        if missing:
            raise ValueError(f"{where} lacks field(s) {missing}: expected 'scene', "
                             "'goal_object_type' and 'state'")
        for key in ("scene", "goal_object_type", "state"):
            read_str(rec, key, where)
        if "optimal_len" in rec:
            read_int(rec, "optimal_len", where)
        if rec["scene"] not in names:
            raise ValueError(f"{where} names scene {rec['scene']!r}, which is not in this "
                             f"SceneSet ({len(names)} scenes, e.g. {list(names)[:3]}); "
                             "was the file made for other scenes?")
        n = names[rec["scene"]]
        try:
            c = category_index(rec["goal_object_type"])
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None
        if n not in index_cache:
            index_cache[n] = key_index(pose[offsets[n]:offsets[n] + counts[n]], counts[n])
        keys = index_cache[n]
        if rec["state"] not in keys:
            raise ValueError(f"{where}: state {rec['state']!r} is not a state of "
                             f"{rec['scene']}; was the file made for other scenes?")
        s = keys[rec["state"]]
        d = int(dist[offsets[n] + s, c])
        if d >= UNREACHABLE or not targets[n, c]:
            if on_unreachable == "skip":
                skipped += 1
                continue
            raise ValueError(f"{where}: target {rec['goal_object_type']} is not a valid "
                             f"target of {rec['scene']} (absent or never visible)")
        if "optimal_len" in rec and int(rec["optimal_len"]) != d:
            raise ValueError(f"{where}: optimal_len {rec['optimal_len']} differs from the "
                             f"scenes' shortest path {d}; was the file made for other scenes?")
        rows.append((n, s, c, d, int(room_type[n])))
    if skipped:
        warnings.warn(f"{source}: skipped {skipped} episode(s) whose target is unreachable",
                      stacklevel=2)
    arr = np.asarray(rows, np.int32).reshape(-1, 5)
    return EpisodeSet(*arr.T.copy(), split=split, seed=seed), skipped
