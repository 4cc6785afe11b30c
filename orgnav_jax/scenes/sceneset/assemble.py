"""Rooms -> SceneSet: the one place a SceneSet is made, and the contract of a scene source.

A scene source (scenes/synthetic: the generator; scenes/offline: the authors' data; or a
new one) delivers each room as a `SourceRoom` of per-room arrays and calls `assemble`,
which lays the rooms out on the flat state axis, computes the expert tables and the
episode targets and returns the SceneSet (numpy arrays). Nothing else makes a SceneSet
from rooms: storage.py saves and loads one (flat.from_padded converts the old padded
files), checks.py validates one.

    scenes = assemble([SourceRoom(...), ...], info=FORMAT_INFO + (("preset", "mine"),))
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np
from tqdm.auto import tqdm

from orgnav_jax.constants import (
    FEATURE_GRID, NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES, TARGETS, category_index,
)
from orgnav_jax.scenes.sceneset.fields import UNREACHABLE
from orgnav_jax.scenes.sceneset.flat import flat_expert_tables
from orgnav_jax.scenes.sceneset.sceneset import SceneSet, storage_offsets

STORE_DTYPE = np.float16   # the stored features (int8 with scales on request: quantize.py)
FEATURE_FIELDS = ("det_box", "det_conf", "appearance", "global_feat")


@dataclasses.dataclass
class SourceRoom:
    """One room as a source delivers it: S states with LOCAL indices 0..S-1."""
    scene_id: int            # AI2-THOR FloorPlan number (or an id named in info "room_names")
    room_type: int           # index into constants.ROOM_TYPES
    split: int               # index into constants.SPLITS
    next_state: np.ndarray   # (S, A) int local successor of each action; a failed move stays
    pose: np.ndarray         # (S, 4) x, z (m), rotation (deg), horizon (deg)
    visible: np.ndarray      # (S, C) bool: category in view and within 1.5 m
    present: np.ndarray      # (C,) bool: the room holds the category
    features: dict | Callable[[dict], None]   # FEATURE_FIELDS -> arrays, or a function
                                               # that writes them (see assemble)


def assemble(rooms: Sequence[SourceRoom], info: tuple = (), *,
             widths: tuple[int, int] | None = None, progress: bool = False,
             **shared) -> SceneSet:
    """The SceneSet of `rooms` (numpy arrays), in their order on the scene axis.

    Each room gives (S its states, C = 22 categories, A = 6 actions):
      next_state (S, A) int, pose (S, 4), visible (S, C) bool, present (C,) bool,
      scene_id, room_type, split (ints), and `features`:
      {"det_box": (S, C, 4) pixels x1 y1 x2 y2, "det_conf": (S, C) (0: no detection),
       "appearance": (S, C, Da), "global_feat": (S, 7, 7, Dg)}; or a function that
      writes them into such a dict of views of the room's rows of the flat arrays,
      called once per room, in order (a source then never holds them twice: the
      importer streams them from hdf5 state by state).
    widths: (Da, Dg), the same for every room; default: those of the first room's
    arrays (give them when its features are a function).
    The features are stored as float16 (STORE_DTYPE). Without `shared` bases they are
    the model's inputs (Da = d, Dg = G); with appearance_proto (C, d), appearance_basis
    (Da, d), global_basis (Dg, G) float32 they are codes the bases decode (features.py).
    info: (key, value) pairs kept as SceneSet.info, starting with fields.FORMAT_INFO,
    then the source's ("preset", name), ("seed", int), ...

    Lays the rooms' states out grouped by split, in room order within a split
    (storage_offsets: a split view is one slice), next_state as global flat int32
    indices; computes dist (T, C) int16 and expert_action (T, C) int8
    (flat_expert_tables) and targets (N, C) (valid_targets).
    Checks each room's shapes (ValueError naming the room); the values (index ranges,
    finite features, ...) are SceneSet.validate's, which save and load run, and which a
    source that hands out an unsaved set runs itself (the importer does).
    """
    for n, room in enumerate(rooms):
        _check_graph(room, n)
    counts = np.array([len(r.pose) for r in rooms], np.int32)
    split = np.array([r.split for r in rooms], np.int32)
    offsets = storage_offsets(split, counts)
    order = np.argsort(offsets, kind="stable")
    fields = {
        "next_state": np.concatenate([rooms[n].next_state.astype(np.int32) + offsets[n]
                                      for n in order]),
        "pose": np.concatenate([rooms[n].pose for n in order]).astype(np.float32),
        "visible": np.concatenate([rooms[n].visible for n in order]).astype(bool),
        **_stored_features(rooms, offsets, counts, widths, progress),
    }
    dist, action = flat_expert_tables(fields["next_state"], fields["visible"], offsets, counts)
    room_type = np.array([r.room_type for r in rooms], np.int32)
    present = np.stack([r.present for r in rooms])
    return SceneSet(
        dist=dist, expert_action=action, present=present,
        targets=valid_targets(room_type, present, dist, offsets, counts),
        state_offset=offsets, state_count=counts, room_type=room_type,
        scene_id=np.array([r.scene_id for r in rooms], np.int32), split=split,
        info=info, **fields, **shared,
    )


def _check_graph(room: SourceRoom, n: int) -> None:
    S, C = len(room.pose), NUM_CATEGORIES
    for name, want in (("next_state", (S, NUM_ACTIONS)), ("pose", (S, 4)),
                       ("visible", (S, C)), ("present", (C,))):
        if np.shape(getattr(room, name)) != want:
            raise ValueError(f"room {n} (scene_id {room.scene_id}): {name} has shape "
                             f"{np.shape(getattr(room, name))}, expected {want}")


def _stored_features(rooms: Sequence[SourceRoom], offsets, counts, widths, progress: bool
                     ) -> dict:
    """FEATURE_FIELDS -> flat (T, ...) STORE_DTYPE arrays, filled room by room."""
    if widths is None:
        if callable(rooms[0].features):
            raise ValueError("assemble: give widths=(Da, Dg) when features are functions")
        widths = (np.shape(rooms[0].features["appearance"])[-1],
                  np.shape(rooms[0].features["global_feat"])[-1])
    T, C, K = int(counts.sum()), NUM_CATEGORIES, FEATURE_GRID
    tails = {"det_box": (C, 4), "det_conf": (C,), "appearance": (C, widths[0]),
             "global_feat": (K, K, widths[1])}
    out = {k: np.zeros((T,) + tails[k], STORE_DTYPE) for k in FEATURE_FIELDS}
    with tqdm(rooms, desc="features", disable=not progress) as bar:
        for n, room in enumerate(bar):
            rows = slice(int(offsets[n]), int(offsets[n]) + int(counts[n]))
            views = {k: out[k][rows] for k in FEATURE_FIELDS}
            if callable(room.features):
                room.features(views)
                continue
            for k in FEATURE_FIELDS:
                if np.shape(room.features[k]) != views[k].shape:
                    raise ValueError(f"room {n} (scene_id {room.scene_id}): feature {k!r} has "
                                     f"shape {np.shape(room.features[k])}, expected "
                                     f"{views[k].shape}")
                views[k][...] = room.features[k]
    return out


def valid_targets(room_type: np.ndarray, present: np.ndarray, dist: np.ndarray,
                  offsets: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(N,) room types, (N, C) present, (T, C) flat dist, (N,) state offsets and counts
    -> (N, C) bool episode targets: a target of the room type (constants.TARGETS),
    present, and reachable (visible from some state; the state graph of a room is
    strongly connected)."""
    of_type = np.zeros((len(ROOM_TYPES), NUM_CATEGORIES), bool)
    for t, names in enumerate(ROOM_TYPES):
        of_type[t, [category_index(c) for c in TARGETS[names]]] = True
    reachable = np.stack([(dist[o:o + k] < UNREACHABLE).any(0)
                          for o, k in zip(np.asarray(offsets), np.asarray(counts))])
    return of_type[room_type] & present & reachable
