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

from orgnav_jax.constants import (
    ACTIONS, CATEGORIES, DONE, NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES, SPLITS, split_index,
)

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
    scene_id: jax.Array        # (N,) int32 AI2-THOR FloorPlan number, or the id of a room
                               #   named in info "room_names" (see scene_names)
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
        """FloorPlanN, or the folder name of a room imported with a splits file (kept in
        info as "room_names" for the ids "room_name_ids")."""
        names = dict(zip(self.meta("room_name_ids", ()), self.meta("room_names", ())))
        return [names.get(int(i), f"FloorPlan{int(i)}") for i in np.asarray(self.scene_id)]

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
        """Check shapes, dtypes and every value the environment relies on; raise a
        one-line ValueError naming the field, the scene (index and FloorPlan name), the
        state and the category of the first bad value. See validate_values."""
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
        if (self.appearance_basis is None) != (self.appearance_proto is None):
            raise ValueError(f"{source}: fields 'appearance_basis' and 'appearance_proto' "
                             "must both be present (synthetic codes) or both absent")
        d = None if self.appearance_basis is None else self.appearance_basis.shape[-1]
        bases = {"global_basis": (self.global_feat.shape[-1], "G"),   # (rows, columns)
                 "appearance_basis": (self.appearance.shape[-1], "d"),
                 "appearance_proto": (C, d)}
        for name, (rows, cols) in bases.items():
            value = getattr(self, name)
            if value is not None and (value.ndim != 2 or value.shape[0] != rows
                                      or isinstance(cols, int) and value.shape[1] != cols):
                raise ValueError(f"{source}: field {name!r} has shape {tuple(value.shape)}, "
                                 f"expected ({rows}, {cols})")
        validate_values(self, source)


# ---------------------------------------------------------------------- validation
_KINDS = {"b": "bool", "iu": "an integer type", "f": "a float type"}
_FIELD_KINDS = {
    "b": ("state_valid", "visible", "present", "targets"),
    "iu": ("next_state", "state_count", "dist", "expert_action", "room_type", "scene_id",
           "split"),
    "f": ("pose", "det_box", "det_conf", "appearance", "global_feat", "appearance_proto",
          "appearance_basis", "global_basis"),
}
_CATEGORY_AXIS_FIELDS = ("visible", "dist", "expert_action", "det_box", "det_conf",
                         "appearance")
# IEEE exponent bits: a value is NaN or Inf exactly when all of them are set. Testing the
# bits of an unsigned view is ~10x faster than np.isfinite on float16.
_EXPONENT = {np.dtype(np.float16): (np.uint16, 0x7C00),
             np.dtype(np.float32): (np.uint32, 0x7F800000),
             np.dtype(np.float64): (np.uint64, 0x7FF0000000000000)}
FINITE_CHUNK = 1 << 22  # elements checked at a time (8 MB of float16): memory-mapped
                        # arrays are streamed, never copied whole


def _nonfinite(block: np.ndarray) -> np.ndarray:
    """Bool mask of the NaN/Inf entries of a contiguous 1-D float block."""
    spec = _EXPONENT.get(block.dtype)
    if spec is None:
        return ~np.isfinite(block)
    utype, mask = spec
    return (block.view(utype) & utype(mask)) == utype(mask)


def first_nonfinite(arr) -> tuple[tuple[int, ...], float] | None:
    """(index, value) of the first NaN/Inf of a float array, or None; reads the array
    in chunks of FINITE_CHUNK elements (a memory map is streamed, not loaded)."""
    arr = np.asarray(arr)
    if arr.size == 0:
        return None
    flat = arr.reshape(-1)  # a view for C-contiguous arrays (np.load, memory maps)
    for lo in range(0, flat.size, FINITE_CHUNK):
        block = np.ascontiguousarray(flat[lo:lo + FINITE_CHUNK])
        bad = _nonfinite(block)
        if bad.any():
            j = int(np.argmax(bad))
            return tuple(int(i) for i in np.unravel_index(lo + j, arr.shape)), float(block[j])
    return None


def _scene(names: list[str], n: int) -> str:
    return f"scene {n} ({names[n]})" if 0 <= n < len(names) else f"scene {n}"


def _where(names: list[str], field: str, index: tuple[int, ...]) -> str:
    """'scene 3 (FloorPlan4) state 17 category Bowl' for an index into `field`."""
    if field == "appearance_proto":
        return f"row {index[0]} ({CATEGORIES[index[0]]})"
    if field in ("appearance_basis", "global_basis"):
        return f"index {index}"
    text = _scene(names, index[0])
    if len(index) > 1:
        text += f" state {index[1]}"
    if field in _CATEGORY_AXIS_FIELDS and len(index) > 2:
        text += f" category {CATEGORIES[index[2]]}"
    return text


def _first(mask: np.ndarray) -> tuple[int, ...] | None:
    if not mask.any():
        return None
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))


def _action_name(a: int) -> str:
    return ACTIONS[a] if 0 <= a < NUM_ACTIONS else str(a)


def validate_values(scenes: SceneSet, source: str = "SceneSet") -> None:
    """The value checks of SceneSet.validate (shapes already checked):

    - dtypes: bool masks, integer indices, float features;
    - state_count in 1..S and state_valid True exactly on the first state_count states;
      room_type, split in range; next_state in [0, S), valid states lead to valid states,
      padding states to themselves;
    - every float field finite (pose, det_box, det_conf, appearance, global_feat and the
      bases if present), streamed in chunks;
    - dist in 0..UNREACHABLE, expert_action in NO_ACTION..DONE, and on valid states the
      expert tables of scenes/expert.py: dist 0 exactly where the category is visible;
      Done exactly where dist is 0; NO_ACTION exactly where dist is UNREACHABLE;
      elsewhere expert_action is a move (0..4, rotations and looks cost 1 like
      MoveAhead) whose successor has dist exactly one less; no move reaches a state more
      than one closer (dist is the shortest path, not just a path). Padding states are
      unreachable (UNREACHABLE, NO_ACTION) and never visible;
    - targets only where the category is present and some valid state has a finite dist.
    """
    N, S = scenes.state_valid.shape
    fields = {f.name: getattr(scenes, f.name) for f in dataclasses.fields(scenes)
              if f.name != "info"}
    for kinds, names in _FIELD_KINDS.items():
        for name in names:
            value = fields[name]
            if value is not None and np.dtype(value.dtype).kind not in kinds:
                raise ValueError(f"{source}: field {name!r} has dtype {value.dtype}, expected "
                                 f"{_KINDS[kinds]}")
    counts = np.asarray(scenes.state_count).astype(np.int64)
    if counts.size and (counts.min() < 1 or counts.max() > S):
        n = int(np.argmax((counts < 1) | (counts > S)))
        raise ValueError(f"{source}: field 'state_count' is {counts[n]} for scene {n}, "
                         f"expected 1..{S} (the padded number of states)")
    names = scenes.scene_names
    valid = np.asarray(scenes.state_valid)
    if not (valid == (np.arange(S)[None] < counts[:, None])).all():
        n = int(np.argmax((valid != (np.arange(S)[None] < counts[:, None])).any(1)))
        raise ValueError(f"{source}: field 'state_valid' must be True exactly on the first "
                         f"state_count[n] states of each scene; it is not for "
                         f"{_scene(names, n)}")
    for name, limit, what in (("room_type", len(ROOM_TYPES), f"an index into {ROOM_TYPES}"),
                              ("split", len(SPLITS), "0 (train), 1 (val), 2 (test)")):
        arr = np.asarray(fields[name])
        bad = (arr < 0) | (arr >= limit)
        if bad.any():
            n = int(np.argmax(bad))
            raise ValueError(f"{source}: field {name!r} is {arr[n]} for {_scene(names, n)}, "
                             f"expected {what}")
    nxt = np.asarray(scenes.next_state)
    if nxt.size and (nxt.min() < 0 or nxt.max() >= S):
        n, s, a = _first((nxt < 0) | (nxt >= S))
        raise ValueError(f"{source}: field 'next_state' holds indices outside [0, {S}): "
                         f"{nxt[n, s, a]} at {_scene(names, n)} state {s} action "
                         f"{_action_name(a)}")

    for name in _FIELD_KINDS["f"]:
        if fields[name] is None:
            continue
        hit = first_nonfinite(fields[name])
        if hit is not None:
            index, value = hit
            value = "NaN" if np.isnan(value) else ("Inf" if value > 0 else "-Inf")
            raise ValueError(f"{source}: field {name!r} holds {value} at "
                             f"{_where(names, name, index)}; expected finite values "
                             "(the data is corrupt: rebuild or re-import it)")

    dist_all, act_all, vis_all = scenes.dist, scenes.expert_action, scenes.visible
    targets, present = np.asarray(scenes.targets), np.asarray(scenes.present)
    C = NUM_CATEGORIES
    for n in range(N):
        k = int(counts[n])
        d = np.asarray(dist_all[n]).astype(np.int32)          # (S, C)
        a = np.asarray(act_all[n]).astype(np.int32)     # (S, C)
        vis = np.asarray(vis_all[n])
        step = nxt[n]                                          # (S, A)

        def where(s, c=None, n=n):
            return (f"{_scene(names, n)} state {s}"
                    + (f" target {CATEGORIES[c]}" if c is not None else ""))
        hit = _first((d < 0) | (d > UNREACHABLE))
        if hit:
            s, c = hit
            raise ValueError(f"{source}: field 'dist' holds {d[s, c]} at {where(s, c)}; "
                             f"expected 0..{UNREACHABLE - 1} (actions to a state where the "
                             f"target is visible) or {UNREACHABLE} (UNREACHABLE)")
        hit = _first((a < NO_ACTION) | (a > DONE))
        if hit:
            s, c = hit
            raise ValueError(f"{source}: field 'expert_action' holds {a[s, c]} at "
                             f"{where(s, c)}; expected {NO_ACTION} (NO_ACTION: no path), "
                             f"0..{DONE - 1} (the first move of a shortest path) or {DONE} "
                             "(Done, where the target is visible)")
        # padding states: self-loops, never visible, unreachable
        hit = _first(step[k:] != np.arange(k, S)[:, None])
        if hit:
            s, m = hit
            raise ValueError(f"{source}: field 'next_state' of padding {where(k + s)} "
                             f"(state_count {k}) leads to {step[k + s, m]} by "
                             f"{_action_name(m)}; padding states must stay put")
        for name, arr, ok in (("visible", vis, False), ("dist", d, UNREACHABLE),
                              ("expert_action", a, NO_ACTION)):
            hit = _first(arr[k:] != ok)
            if hit:
                s, c = hit
                raise ValueError(f"{source}: field {name!r} is {arr[k + s, c]} at padding "
                                 f"{where(k + s, c)} (state_count {k}); expected {ok}")
        d, a, vis, step = d[:k], a[:k], vis[:k], step[:k]
        hit = _first(step >= k)
        if hit:
            s, m = hit
            raise ValueError(f"{source}: field 'next_state' leads from valid {where(s)} by "
                             f"{_action_name(m)} to padding state {step[s, m]} (the scene "
                             f"has {k} states)")
        hit = _first((d == 0) != vis)
        if hit:
            s, c = hit
            raise ValueError(f"{source}: field 'dist' is {d[s, c]} at {where(s, c)}, where "
                             f"the target is {'' if vis[s, c] else 'not '}visible; expected "
                             "dist 0 exactly where the target is visible")
        for cond, text in (((a == DONE) != (d == 0), "Done exactly where dist is 0"),
                           ((a == NO_ACTION) != (d == UNREACHABLE),
                            f"NO_ACTION ({NO_ACTION}) exactly where dist is UNREACHABLE")):
            hit = _first(cond)
            if hit:
                s, c = hit
                raise ValueError(f"{source}: fields 'expert_action' and 'dist' disagree at "
                                 f"{where(s, c)}: expert_action {_action_name(a[s, c])}, dist "
                                 f"{d[s, c]}; expected {text}")
        moving = (d > 0) & (d < UNREACHABLE)
        cols = np.arange(C)[None, :]
        succ = step[np.arange(k)[:, None], np.clip(a, 0, DONE)]     # (k, C)
        hit = _first(moving & (d[succ, cols] != d - 1))
        if hit:
            s, c = hit
            t = succ[s, c]
            raise ValueError(
                f"{source}: fields 'expert_action' and 'dist' disagree at {where(s, c)}: "
                f"dist {d[s, c]}, expert_action {_action_name(a[s, c])} leads to state {t} "
                f"at dist {d[t, c]}; expected {d[s, c] - 1} (the expert action must start a "
                "shortest path)")
        for m in range(DONE):
            after = d[step[:, m]]                                   # (k, C)
            hit = _first(d > after + 1)
            if hit:
                s, c = hit
                raise ValueError(
                    f"{source}: field 'dist' is {d[s, c]} at {where(s, c)}, but "
                    f"{_action_name(m)} leads to state {step[s, m]} at dist {after[s, c]}: "
                    "dist is not the shortest path length")
        bad = targets[n] & ~(present[n] & (d < UNREACHABLE).any(0))
        if bad.any():
            c = int(np.argmax(bad))
            raise ValueError(f"{source}: field 'targets' marks {CATEGORIES[c]} in "
                             f"{_scene(names, n)}, which is absent or never visible from a "
                             "reachable state; expected targets only where present and "
                             "reachable")
