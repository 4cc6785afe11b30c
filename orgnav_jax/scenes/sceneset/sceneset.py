"""The SceneSet: every room of a benchmark in one pytree, per-state arrays unpadded.

Axes: N scenes, T states (the rooms' states one after another: one flat axis, nothing
padded to the largest room), A = 6 actions, C = 22 categories. Room n owns the flat
states state_offset[n] .. state_offset[n] + state_count[n] - 1; the rooms' ranges
partition 0..T-1 but need not follow the scene order (assemble.py stores the rooms grouped
by split, so that a split view is one contiguous run: a slice of a memory map, no copy).

Index convention: `next_state` holds GLOBAL flat indices (a room's moves stay inside
its range); the environment's EnvState.state and Observation.state are global flat
indices; episodes (EpisodeSet, episode files) and `state_count` are per room, LOCAL:
global = state_offset[scene] + local (SceneSet.global_state).

Large features are stored compactly and decoded inside jit by
`orgnav_jax.scenes.sceneset.features`: for synthetic scenes `global_feat` and `appearance` hold
low-dimensional 16-bit codes and the `*_basis` / `appearance_proto` arrays project them
to the preset's widths (G, d); for imported offline data the bases are None and the
stored arrays are the features themselves, float16, or int8 with a per-channel float32
scale (`global_scale` (Dg,), `appearance_scale` (Da,): feature = int8 value * scale).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from orgnav_jax.constants import ROOM_TYPES, split_index
from orgnav_jax.scenes.sceneset.checks import validate_shapes, validate_values
from orgnav_jax.scenes.sceneset.fields import PER_SCENE_FIELDS, PER_STATE_FIELDS


@struct.dataclass
class SceneSet:
    """N scenes, T states on one flat axis (see the module docstring)."""
    next_state: jax.Array      # (T, A) int32 successor (global flat index); failed move: stays
    pose: jax.Array            # (T, 4) float32 x, z (m), rotation (deg), horizon (deg)
    visible: jax.Array         # (T, C) bool: category c in view and within 1.5 m
    present: jax.Array         # (N, C) bool: the scene has category c
    targets: jax.Array         # (N, C) bool: valid episode targets (a target of the room
                               #   type, present, and visible from some reachable state)
    state_offset: jax.Array    # (N,) int32 first flat state of each scene
    state_count: jax.Array     # (N,) int32 states of each scene
    dist: jax.Array            # (T, C) int16 shortest path (actions) to a visible state
    expert_action: jax.Array   # (T, C) int8 first action of such a path; Done if visible
    det_box: jax.Array         # (T, C, 4) float16 best box per category, pixels (x1,y1,x2,y2)
    det_conf: jax.Array        # (T, C) float16 its confidence; 0 = no detection
    appearance: jax.Array      # (T, C, Da) float16 or int8 code (or feature if no basis)
    global_feat: jax.Array     # (T, 7, 7, Dg) float16 or int8 code (or feature if no basis)
    room_type: jax.Array       # (N,) int32 index into ROOM_TYPES
    scene_id: jax.Array        # (N,) int32 AI2-THOR FloorPlan number, or the id of a room
                               #   named in info "room_names" (see scene_names)
    split: jax.Array           # (N,) int32 index into SPLITS
    appearance_proto: jax.Array | None = None  # (C, d) float32 class prototypes
    appearance_basis: jax.Array | None = None  # (Da, d) float32 view-noise basis
    global_basis: jax.Array | None = None      # (Dg, G) float32 fixed random projection
    global_scale: jax.Array | None = None      # (Dg,) float32 int8 dequantization scale
    appearance_scale: jax.Array | None = None  # (Da,) float32 int8 dequantization scale
    info: tuple = struct.field(pytree_node=False, default=())  # (("preset", ..), ("seed", ..))

    # ------------------------------------------------------------------ sizes
    @property
    def num_scenes(self) -> int:
        return int(self.state_count.shape[0])

    @property
    def num_states(self) -> int:
        """T, the states of all rooms together (the flat axis; no padding)."""
        return int(self.next_state.shape[0])

    @property
    def max_states(self) -> int:
        """States of the largest room."""
        return int(np.asarray(self.state_count).max()) if self.num_scenes else 0

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
        """FloorPlanN, or the folder name of a room imported with a splits file (kept in
        info as "room_names" for the ids "room_name_ids")."""
        names = dict(zip(self.meta("room_name_ids", ()), self.meta("room_names", ())))
        return [names.get(int(i), f"FloorPlan{int(i)}") for i in np.asarray(self.scene_id)]

    @property
    def state_scene(self) -> np.ndarray:
        """(T,) int32 numpy: the scene of every flat state (computed, host side)."""
        off, cnt = np.asarray(self.state_offset), np.asarray(self.state_count)
        order = np.argsort(off, kind="stable")
        return np.repeat(order.astype(np.int32), cnt[order])

    def state_slice(self, n: int) -> slice:
        """The flat states of scene n: per-state arrays [state_slice(n)] are its rows."""
        lo = int(np.asarray(self.state_offset)[n])
        return slice(lo, lo + int(np.asarray(self.state_count)[n]))

    def global_state(self, scene, local):
        """Flat index of a scene's local state index (numpy or jax, broadcasts; jittable)."""
        return self.state_offset[scene] + local

    def meta(self, key: str, default=None):
        """A value from `info` (preset, seed, format version, ...)."""
        return dict(self.info).get(key, default)

    # ------------------------------------------------------------------ views
    def select(self, index) -> "SceneSet":
        """The scenes at `index` (array of ints or bool mask), in that order, holding only
        their own states. The view keeps the set's storage order of the rooms' states, so
        rooms stored one after another (a split of a built or imported set) are one slice:
        of a memory-mapped set, a view of the map (nothing copied); otherwise only the
        selected rows are gathered. state_offset and next_state are re-based."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        if index.size == 0:
            raise ValueError("selection is empty: no scene matches")
        off = np.asarray(self.state_offset).astype(np.int64)[index]
        cnt = np.asarray(self.state_count).astype(np.int64)[index]
        order = np.argsort(off, kind="stable")
        new_off = np.empty_like(off)
        new_off[order] = np.cumsum(cnt[order]) - cnt[order]
        runs = []                                   # (lo, hi) of the kept rows, merged
        for lo, k in zip(off[order], cnt[order]):
            if runs and runs[-1][1] == lo:
                runs[-1][1] = lo + k
            else:
                runs.append([lo, lo + k])
        out = {"state_offset": new_off.astype(np.int32)}
        for name in PER_STATE_FIELDS:
            out[name] = take_rows(getattr(self, name), runs)
        shift = np.repeat(off[order] - new_off[order], cnt[order])      # old - new
        if shift.any():
            out["next_state"] = (np.asarray(out["next_state"])
                                 - shift[:, None].astype(np.int32)).astype(np.int32)
        for name in PER_SCENE_FIELDS:
            if name != "state_offset":
                out[name] = np.asarray(getattr(self, name))[index]
        return self.replace(**out)

    def split_view(self, name: str) -> "SceneSet":
        """Only the scenes of one split ('train', 'val' or 'test') and their states."""
        return self.select(np.asarray(self.split) == split_index(name))

    def room_type_view(self, name: str) -> "SceneSet":
        """Only the scenes of one room type and their states."""
        if name not in ROOM_TYPES:
            raise ValueError(f"unknown room type {name!r}: expected one of {list(ROOM_TYPES)}")
        return self.select(np.asarray(self.room_type) == ROOM_TYPES.index(name))

    def to_device(self) -> "SceneSet":
        """Every array as a jax.Array, each put on the device once (jax.Arrays are kept).
        Read-only numpy arrays (a memory-mapped set or its views) go through
        jax.device_put, which on the CPU aliases suitably aligned host memory instead of
        copying it: the device array is the map itself. Writable arrays are copied
        (jnp.asarray), so later writes to them never reach the device arrays (device_put
        aliases those too, whatever may_alias says, in jax 0.10)."""
        def put(x):
            if isinstance(x, jax.Array):
                return x
            x = np.asarray(x)
            return jnp.asarray(x) if x.flags.writeable else jax.device_put(x)
        return jax.tree_util.tree_map(put, self)

    def validate(self, source: str = "SceneSet") -> None:
        """Check shapes, dtypes and every value the environment relies on; raise a
        one-line ValueError naming the field, the scene (index and FloorPlan name), the
        state and the category of the first bad value (checks.validate_values)."""
        validate_shapes(self, source)
        validate_values(self, source)


def take_rows(arr, runs) -> np.ndarray:
    """Rows lo..hi-1 of every (lo, hi) run of a per-state array, in order: a view (no
    copy) for a single run, else one array holding only those rows."""
    arr = np.asarray(arr) if not isinstance(arr, np.ndarray) else arr
    if len(runs) == 1:
        lo, hi = runs[0]
        return arr[lo:hi]
    return np.concatenate([arr[lo:hi] for lo, hi in runs])


def storage_offsets(split, state_count) -> np.ndarray:
    """(N,) int32 offsets that store the rooms grouped by split (train, val, test), in
    scene order within a split, so that each split view is one contiguous run of states.
    Every builder of SceneSets (synthetic, offline import, conversion) uses this."""
    split, cnt = np.asarray(split), np.asarray(state_count).astype(np.int64)
    order = np.argsort(split, kind="stable")
    off = np.empty(len(cnt), np.int64)
    off[order] = np.cumsum(cnt[order]) - cnt[order]
    if off.size and off.max() + cnt.max() >= 2 ** 31:
        raise ValueError(f"{int(cnt.sum())} states: more than int32 flat indices hold")
    return off.astype(np.int32)
