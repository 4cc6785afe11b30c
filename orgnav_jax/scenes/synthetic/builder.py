"""Build a SceneSet from a preset and a seed: rooms -> observations -> per-room arrays,
assembled into a SceneSet (sceneset/assemble.py: flat layout, expert tables)."""

from __future__ import annotations

import dataclasses

import numpy as np
from tqdm.auto import tqdm

from orgnav_jax.constants import DEFAULT_SCENE_PRESET, NUM_CATEGORIES, ROOM_TYPE_INDEX, SPLIT_INDEX
from orgnav_jax.scenes.sceneset import assemble
from orgnav_jax.scenes.sceneset.fields import FORMAT_INFO
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.synthetic import detector, geometry, global_view
from orgnav_jax.scenes.synthetic.catalog import ANCHOR_PROBABILITY
from orgnav_jax.scenes.synthetic.layout import Room, generate_room
from orgnav_jax.scenes.synthetic.perception import Perception, degrade_detections, degrade_global
from orgnav_jax.scenes.synthetic.presets import ScenePreset, episode_distance_info, get_preset


@dataclasses.dataclass
class RoomArrays:
    """A generated room's arrays (S = 16 * reachable cells); .room() for assembly."""
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

    def room(self) -> assemble.SourceRoom:
        """This room as the SceneSet assembly takes it (features: the 16-bit codes)."""
        return assemble.SourceRoom(
            scene_id=self.floorplan, room_type=self.room_type, split=self.split,
            next_state=self.next_state, pose=self.pose, visible=self.visible,
            present=self.present,
            features={k: getattr(self, k) for k in assemble.FEATURE_FIELDS})


def room_detections(room: Room, seed: int, cells: np.ndarray, poses: np.ndarray,
                    perception: Perception = Perception()):
    """Line of sight and the detector (with `perception`'s knobs) run on every state of
    a room.

    Returns seen (S, K) and horizontal distance (S, K) per object instance, and
    det_box (S, C, 4), det_conf (S, C), appearance code (S, C, Da) per category.
    """
    los = geometry.line_of_sight(room.block_height, cells, room.obj_center, room.obj_size,
                                 detector.MAX_DETECT_DISTANCE)
    seen, dist, _ = geometry.object_visibility(poses, cells, los, room.obj_center)
    boxes = detector.project_boxes(poses, room.obj_center, room.obj_size, room.obj_height)
    det_rng = np.random.default_rng([seed, room.floorplan, 1])
    det_box, det_conf, code = detector.detect(det_rng, seen, dist, boxes, room.obj_category,
                                              perception)
    # confusions and jitter draw from a stream of their own: the detector's is unchanged
    det_box, det_conf, code = degrade_detections(
        det_box, det_conf, code, perception, np.random.default_rng([seed, room.floorplan, 3]))
    return seen, dist, det_box, det_conf, code


def room_arrays(seed: int, floorplan: int, split: str, room: Room | None = None,
                room_sizes: str = "default",
                anchor_probability: float = ANCHOR_PROBABILITY,
                perception: Perception = Perception()) -> RoomArrays:
    """Everything precomputed for one room (pure function of seed, floorplan, the
    room-size profile, the anchor probability and the perception knobs)."""
    room = room if room is not None else generate_room(
        seed, floorplan, room_sizes=room_sizes, anchor_probability=anchor_probability)
    cells = geometry.reachable_cells(room.reachable)
    poses = geometry.state_poses(cells)
    seen, dist, det_box, det_conf, app_code = room_detections(room, seed, cells, poses,
                                                              perception)
    global_feat = degrade_global(global_view.global_codes(room, cells), perception,
                                 np.random.default_rng([seed, floorplan, 4]))
    present = np.zeros(NUM_CATEGORIES, bool)
    present[room.obj_category] = True
    return RoomArrays(
        floorplan=floorplan, room_type=ROOM_TYPE_INDEX[room.room_type],
        split=SPLIT_INDEX[split],
        next_state=geometry.transitions(cells, room.wall.shape), pose=poses,
        visible=geometry.category_visible(seen, dist, room.obj_category, NUM_CATEGORIES),
        present=present, det_box=det_box, det_conf=det_conf, appearance=app_code,
        global_feat=global_feat,
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
    """The SceneSet of these rooms (assemble.assemble; extra: info and the bases)."""
    return assemble.assemble([r.room() for r in rooms], **extra)


def build(preset: str | ScenePreset = DEFAULT_SCENE_PRESET, seed: int = 0, *,
          progress: bool = False, **overrides) -> SceneSet:
    """Generate the synthetic benchmark: a SceneSet of numpy arrays.

    preset: a name of SCENE_PRESETS (default constants.DEFAULT_SCENE_PRESET) or a
    ScenePreset; overrides replace preset fields (e.g. rooms_per_type=(4, 1, 1)). The
    same (preset, seed) gives identical arrays.
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
                         anchor_probability=p.anchor_probability, perception=p.perception)
             for fp, _, split in tqdm(plans, desc=f"rooms ({p.name})", disable=not progress,
                                      unit="room")]
    return stack_rooms(rooms, info=preset_info(p, seed), **feature_bases(p))


def preset_info(preset: ScenePreset, seed: int) -> tuple:
    """The info pairs a set built from (preset, seed) records: the format, the preset's
    name, the seed, rooms per type, and every field of its definition that differs from
    the defaults (room sizes and count, anchor probability, perception knobs, episode
    distances); the cache (cache.py) compares a cached set's info with these on every
    load."""
    p = preset
    info = FORMAT_INFO + (("preset", p.name), ("seed", int(seed)),
                          ("rooms_per_type", tuple(p.rooms_per_type)))
    if p.room_sizes != "default" or p.num_rooms is not None:
        info += (("room_sizes", p.room_sizes), ("num_rooms", len(p.floorplans())))
    if p.anchor_probability != ANCHOR_PROBABILITY:     # (default sets keep their info)
        info += (("anchor_probability", float(p.anchor_probability)),)
    info += tuple(("perception." + k, v) for k, v in p.perception.changed().items())
    return info + episode_distance_info(p)
