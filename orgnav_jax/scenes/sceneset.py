"""The SceneSet: every room of a benchmark stacked into one pytree of padded arrays.

Axes: N scenes, S states (padded to the largest room), A = 6 actions, C = 22
categories. Padding states have state_valid False, transition to themselves, are never
visible and are unreachable (dist = UNREACHABLE, expert_action = NO_ACTION).

Large features are stored compactly (16-bit) and decoded inside jit by
`orgnav_jax.scenes.features`: for synthetic scenes `global_feat` and `appearance` hold
low-dimensional codes and the `*_basis` / `appearance_proto` arrays project them to the
preset's widths (G, d); for imported offline data the bases are None and the stored
arrays are the features themselves.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from flax import struct

from orgnav_jax.constants import NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES, SPLITS, split_index

UNREACHABLE = 32767   # dist sentinel (int16 max): no state where the category is visible can be reached
NO_ACTION = -1        # expert_action sentinel for unreachable targets and padding states
PER_STATE_FIELDS = ("next_state", "state_valid", "pose", "visible", "dist", "expert_action",
                    "det_box", "det_conf", "appearance", "global_feat")
SHARED_FIELDS = ("appearance_proto", "appearance_basis", "global_basis", "info")


@struct.dataclass
class SceneSet:
    """Padded arrays of N scenes (see module docstring for the feature encoding)."""
    next_state: jax.Array      # (N, S, A) int32 successor state; a failed move stays put
    state_valid: jax.Array     # (N, S) bool, False on padding
    pose: jax.Array            # (N, S, 4) float32 x, z (m), rotation (deg), horizon (deg)
    visible: jax.Array         # (N, S, C) bool: category c in view and within 1.5 m
    present: jax.Array         # (N, C) bool: the scene has category c
    targets: jax.Array         # (N, C) bool: valid episode targets (a target of the room
                               #   type, present, and visible from some reachable state)
    state_count: jax.Array     # (N,) int32 valid states; they are the first ones
    dist: jax.Array            # (N, S, C) int16 shortest path (actions) to a visible state
    expert_action: jax.Array   # (N, S, C) int8 first action of such a path; Done if visible
    det_box: jax.Array         # (N, S, C, 4) float16 best box per category, pixels (x1,y1,x2,y2)
    det_conf: jax.Array        # (N, S, C) float16 its confidence; 0 = no detection
    appearance: jax.Array      # (N, S, C, Da) float16 appearance code (or feature if no basis)
    global_feat: jax.Array     # (N, S, 7, 7, Dg) float16 global code (or feature if no basis)
    room_type: jax.Array       # (N,) int32 index into ROOM_TYPES
    scene_id: jax.Array        # (N,) int32 AI2-THOR FloorPlan number
    split: jax.Array           # (N,) int32 index into SPLITS
    appearance_proto: jax.Array | None = None  # (C, d) float32 class prototypes
    appearance_basis: jax.Array | None = None  # (Da, d) float32 view-noise basis
    global_basis: jax.Array | None = None      # (Dg, G) float32 fixed random projection
    info: tuple = struct.field(pytree_node=False, default=())  # (("preset", ..), ("seed", ..))

    # ------------------------------------------------------------------ sizes
    @property
    def num_scenes(self) -> int:
        return int(self.next_state.shape[0])

    @property
    def num_states(self) -> int:
        """S, the padded number of states."""
        return int(self.next_state.shape[1])

    @property
    def global_dim(self) -> int:
        """G, channels of the decoded global feature map."""
        return int((self.global_basis if self.global_basis is not None
                    else self.global_feat).shape[-1])

    @property
    def appearance_dim(self) -> int:
        """d, width of the decoded per-category appearance feature."""
        return int((self.appearance_proto if self.appearance_proto is not None
                    else self.appearance).shape[-1])

    @property
    def scene_names(self) -> list[str]:
        return [f"FloorPlan{int(i)}" for i in np.asarray(self.scene_id)]

    def meta(self, key: str, default=None):
        """A value from `info` (preset, seed, format version, ...)."""
        return dict(self.info).get(key, default)

    # ------------------------------------------------------------------ views
    def select(self, index) -> "SceneSet":
        """The scenes at `index` (array of ints or bool mask), with S trimmed to the
        largest selected room."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        if index.size == 0:
            raise ValueError("selection is empty: no scene matches")
        s_max = int(np.asarray(self.state_count)[index].max())
        out = {}
        for f in dataclasses.fields(self):
            if f.name in SHARED_FIELDS:
                continue
            a = np.asarray(getattr(self, f.name))[index]
            out[f.name] = a[:, :s_max] if f.name in PER_STATE_FIELDS else a
        return self.replace(**out)

    def split_view(self, name: str) -> "SceneSet":
        """Only the scenes of one split ('train', 'val' or 'test')."""
        return self.select(np.asarray(self.split) == split_index(name))

    def room_type_view(self, name: str) -> "SceneSet":
        """Only the scenes of one room type."""
        if name not in ROOM_TYPES:
            raise ValueError(f"unknown room type {name!r}: expected one of {list(ROOM_TYPES)}")
        return self.select(np.asarray(self.room_type) == ROOM_TYPES.index(name))

    def to_device(self) -> "SceneSet":
        """Every array as a jax.Array (arrays loaded from disk are numpy)."""
        return jax.tree_util.tree_map(jax.numpy.asarray, self)

    def validate(self, source: str = "SceneSet") -> None:
        """Check shapes and value ranges; raise ValueError naming the field."""
        N, S = self.state_valid.shape if self.state_valid.ndim == 2 else (None, None)
        if N is None:
            raise ValueError(f"{source}: field 'state_valid' must be (N, S), "
                             f"got shape {self.state_valid.shape}")
        C, A = NUM_CATEGORIES, NUM_ACTIONS
        expect = {
            "next_state": (N, S, A), "pose": (N, S, 4), "visible": (N, S, C),
            "present": (N, C), "targets": (N, C), "state_count": (N,), "dist": (N, S, C), "expert_action": (N, S, C),
            "det_box": (N, S, C, 4), "det_conf": (N, S, C), "room_type": (N,),
            "scene_id": (N,), "split": (N,),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"{source}: field {name!r} has shape {got}, expected {shape} "
                                 "(N scenes, S states, A=6 actions, C=22 categories)")
        if tuple(self.appearance.shape[:3]) != (N, S, C):
            raise ValueError(f"{source}: field 'appearance' has shape {self.appearance.shape}, "
                             f"expected ({N}, {S}, {C}, d)")
        if tuple(self.global_feat.shape[:4]) != (N, S, 7, 7):
            raise ValueError(f"{source}: field 'global_feat' has shape {self.global_feat.shape},"
                             f" expected ({N}, {S}, 7, 7, G)")
        counts = np.asarray(self.state_count)
        valid = np.asarray(self.state_valid)
        if not (valid == (np.arange(S)[None] < counts[:, None])).all():
            raise ValueError(f"{source}: field 'state_valid' must be True exactly on the first "
                             "state_count[n] states of each scene")
        nxt = np.asarray(self.next_state)
        if nxt.size and (nxt.min() < 0 or nxt.max() >= S):
            raise ValueError(f"{source}: field 'next_state' holds indices outside [0, {S})")
        if np.asarray(self.split).size and not np.isin(np.asarray(self.split),
                                                        range(len(SPLITS))).all():
            raise ValueError(f"{source}: field 'split' must hold 0 (train), 1 (val), 2 (test)")
