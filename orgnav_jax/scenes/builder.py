"""Build a SceneSet from a preset and a seed: rooms -> observations -> flat arrays ->
expert tables."""

from __future__ import annotations

import dataclasses

import numpy as np
from tqdm.auto import tqdm

from orgnav_jax.constants import (
    NUM_CATEGORIES, ROOM_TYPE_INDEX, ROOM_TYPES, SPLIT_INDEX, TARGETS,
    category_index,
)
from orgnav_jax.scenes import detector, geometry, global_view
from orgnav_jax.scenes.flat import flat_expert_tables
from orgnav_jax.scenes.catalog import ANCHOR_PROBABILITY
from orgnav_jax.scenes.layout import Room, generate_room
from orgnav_jax.scenes.presets import ScenePreset, get_preset
from orgnav_jax.scenes.sceneset import (
    FORMAT_NAME, FORMAT_VERSION, UNREACHABLE, SceneSet, storage_offsets,
)

STORE_DTYPE = np.float16


@dataclasses.dataclass
class RoomArrays:
    """Per-room arrays before stacking; S = 16 * reachable cells."""
    floorplan: int
    room_type: int
    split: int
    next_state: np.ndarray   # (S, A)
    pose: np.ndarray         # (S, 4)
    visible: np.ndarray      # (S, C)
    present: np.ndarray      # (C,)
    det_box: np.ndarray      # (S, C, 4)
    det_conf: np.ndarray     # (S, C)
    appearance: np.ndarray   # (S, C, Da)
    global_feat: np.ndarray  # (S, 7, 7, Dg)


def room_detections(room: Room, seed: int, cells: np.ndarray, poses: np.ndarray):
    """Line of sight and the detector run on every state of a room.

    Returns seen (S, K) and horizontal distance (S, K) per object instance, and
    det_box (S, C, 4), det_conf (S, C), appearance code (S, C, Da) per category.
    """
    los = geometry.line_of_sight(room.block_height, cells, room.obj_center, room.obj_size,
                                 detector.MAX_DETECT_DISTANCE)
    seen, dist, _ = geometry.object_visibility(poses, cells, los, room.obj_center)
    boxes = detector.project_boxes(poses, room.obj_center, room.obj_size, room.obj_height)
    det_rng = np.random.default_rng([seed, room.floorplan, 1])
    det_box, det_conf, code = detector.detect(det_rng, seen, dist, boxes, room.obj_category)
    return seen, dist, det_box, det_conf, code


def room_arrays(seed: int, floorplan: int, split: str, room: Room | None = None,
                room_sizes: str = "default",
                anchor_probability: float = ANCHOR_PROBABILITY) -> RoomArrays:
    """Everything precomputed for one room (pure function of seed, floorplan, the
    room-size profile and the anchor probability)."""
    room = room if room is not None else generate_room(
        seed, floorplan, room_sizes=room_sizes, anchor_probability=anchor_probability)
    cells = geometry.reachable_cells(room.reachable)
    poses = geometry.state_poses(cells)
    seen, dist, det_box, det_conf, app_code = room_detections(room, seed, cells, poses)
    present = np.zeros(NUM_CATEGORIES, bool)
    present[room.obj_category] = True
    return RoomArrays(
        floorplan=floorplan, room_type=ROOM_TYPE_INDEX[room.room_type],
        split=SPLIT_INDEX[split],
        next_state=geometry.transitions(cells, room.wall.shape), pose=poses,
        visible=geometry.category_visible(seen, dist, room.obj_category, NUM_CATEGORIES),
        present=present, det_box=det_box, det_conf=det_conf, appearance=app_code,
        global_feat=global_view.global_codes(room, cells),
    )


def feature_bases(preset: ScenePreset) -> dict[str, np.ndarray]:
    """Fixed projections for the preset's widths (the same for every scene seed, like a
    pretrained backbone): class prototypes (C, d), noise basis (Da, d), global (Dg, G)."""
    rng = np.random.default_rng([preset.global_dim, preset.appearance_dim, 2020])
    d, G = preset.appearance_dim, preset.global_dim
    da, dg = detector.APPEARANCE_CODE_DIM, global_view.GLOBAL_CODE_DIM
    return {
        "appearance_proto": rng.normal(0.3, 1.0, (NUM_CATEGORIES, d)).astype(np.float32),
        "appearance_basis": (rng.normal(0, 1, (da, d)) * 0.8 / np.sqrt(da)).astype(np.float32),
        "global_basis": (rng.normal(0, 1, (dg, G)) * 2 / np.sqrt(dg)).astype(np.float32),
    }


def stack_rooms(rooms: list[RoomArrays], **extra) -> SceneSet:
    """Concatenate rooms on one flat state axis (grouped by split,
    sceneset.storage_offsets) and compute the expert tables."""
    counts = np.array([len(r.pose) for r in rooms], np.int32)
    split = np.array([r.split for r in rooms], np.int32)
    offsets = storage_offsets(split, counts)
    order = np.argsort(offsets, kind="stable")
    fields = {
        "next_state": np.concatenate([rooms[n].next_state.astype(np.int32) + offsets[n]
                                      for n in order]),
        "pose": np.concatenate([rooms[n].pose for n in order]).astype(np.float32),
        "visible": np.concatenate([rooms[n].visible for n in order]).astype(bool),
    }
    for name in ("det_box", "det_conf", "appearance", "global_feat"):
        fields[name] = np.concatenate([getattr(rooms[n], name) for n in order]
                                      ).astype(STORE_DTYPE)
    dist, action = flat_expert_tables(fields["next_state"], fields["visible"], offsets, counts)
    room_type = np.array([r.room_type for r in rooms], np.int32)
    present = np.stack([r.present for r in rooms])
    return SceneSet(
        dist=dist, expert_action=action, present=present,
        targets=valid_targets(room_type, present, dist, offsets, counts),
        state_offset=offsets, state_count=counts, room_type=room_type,
        scene_id=np.array([r.floorplan for r in rooms], np.int32), split=split,
        **fields, **extra,
    )


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


def build(preset: str | ScenePreset = "small", seed: int = 0, *, progress: bool = False,
          **overrides) -> SceneSet:
    """Generate the synthetic benchmark: a SceneSet of numpy arrays.

    preset: 'small', 'paper', 'tiny' or a ScenePreset; overrides replace preset fields
    (e.g. rooms_per_type=(4, 1, 1)). The same (preset, seed) gives identical arrays.
    A raw preset ('large') is refused: it is written to disk by scenes.build_to; with
    raw=False it is built here with codes and bases like the others.
    """
    p = get_preset(preset, **overrides)
    if p.raw:
        raise ValueError(f"preset {p.name!r} stores raw features (paper widths: about 72 KB "
                         "per state, ~6 GB for its 40 rooms) and is only written to disk, "
                         "room by room: python -m orgnav_jax.scenes build --preset "
                         f"{p.name} --out DIR (or scenes.build_to), then load DIR")
    plans = p.floorplans()
    rooms = [room_arrays(seed, fp, split, room_sizes=p.room_sizes,
                         anchor_probability=p.anchor_probability)
             for fp, _, split in tqdm(plans, desc=f"rooms ({p.name})", disable=not progress,
                                      unit="room")]
    info = (("format", FORMAT_NAME), ("version", FORMAT_VERSION), ("preset", p.name),
            ("seed", int(seed)), ("rooms_per_type", tuple(p.rooms_per_type)))
    if p.room_sizes != "default" or p.num_rooms is not None:
        info += (("room_sizes", p.room_sizes), ("num_rooms", len(plans)))
    if p.anchor_probability != ANCHOR_PROBABILITY:     # (default sets keep their info)
        info += (("anchor_probability", float(p.anchor_probability)),)
    return stack_rooms(rooms, info=info, **{k: v for k, v in feature_bases(p).items()})
