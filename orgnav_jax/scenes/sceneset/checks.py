"""SceneSet.validate: shapes, dtypes and every value the environment relies on.

Errors are one line naming the field, the scene (index and FloorPlan name), the state
(the room's own, local index) and the category of the first bad value. Float features are
streamed in chunks; of a memory-mapped set the pages read are released again (madvise),
so validating a set on load does not leave it resident in the process.
"""

from __future__ import annotations

import dataclasses
import mmap

import numpy as np

from orgnav_jax.constants import (
    ACTIONS, CATEGORIES, DONE, NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES, SPLITS,
)
from orgnav_jax.scenes.sceneset.fields import NO_ACTION, SCALE_OF, UNREACHABLE

_KINDS = {"b": "bool", "iu": "an integer type", "f": "a float type", "fi": "float or int8"}
_FIELD_KINDS = {
    "b": ("visible", "present", "targets"),
    "iu": ("next_state", "state_offset", "state_count", "dist", "expert_action", "room_type",
           "scene_id", "split"),
    "f": ("pose", "det_box", "det_conf", "appearance_proto", "appearance_basis",
          "global_basis", "global_scale", "appearance_scale"),
    "fi": ("appearance", "global_feat"),
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


def _shape_error(source, name, got, want) -> ValueError:
    return ValueError(f"{source}: field {name!r} has shape {tuple(got)}, expected {want} "
                      "(N scenes, T states of all rooms, A=6 actions, C=22 categories)")


def validate_shapes(scenes, source: str = "SceneSet") -> None:
    """Shapes of every field: per-state (T, ...), per-scene (N, ...), the bases and the
    int8 scales; int8 features need their scale, float features must not have one."""
    if scenes.next_state.ndim != 2:
        raise _shape_error(source, "next_state", scenes.next_state.shape, "(T, 6)")
    if scenes.state_count.ndim != 1:
        raise _shape_error(source, "state_count", scenes.state_count.shape, "(N,)")
    T, N = scenes.next_state.shape[0], scenes.state_count.shape[0]
    C, A = NUM_CATEGORIES, NUM_ACTIONS
    expect = {
        "next_state": (T, A), "pose": (T, 4), "visible": (T, C), "dist": (T, C),
        "expert_action": (T, C), "det_box": (T, C, 4), "det_conf": (T, C),
        "present": (N, C), "targets": (N, C), "state_offset": (N,), "state_count": (N,),
        "room_type": (N,), "scene_id": (N,), "split": (N,),
    }
    for name, shape in expect.items():
        got = tuple(getattr(scenes, name).shape)
        if got != shape:
            raise _shape_error(source, name, got, shape)
    if tuple(scenes.appearance.shape[:2]) != (T, C) or scenes.appearance.ndim != 3:
        raise _shape_error(source, "appearance", scenes.appearance.shape, f"({T}, {C}, d)")
    if tuple(scenes.global_feat.shape[:3]) != (T, 7, 7) or scenes.global_feat.ndim != 4:
        raise _shape_error(source, "global_feat", scenes.global_feat.shape, f"({T}, 7, 7, G)")
    for name, stored, dim, width in (
            ("global_feat", scenes.global_feat.shape[-1], "global_dim", scenes.global_dim),
            ("appearance", scenes.appearance.shape[-1], "appearance_dim",
             scenes.appearance_dim)):
        if min(stored, width) < 1:     # a model over 0 channels divides by zero
            raise ValueError(f"{source}: field {name!r} has {min(stored, width)} feature "
                             f"channels ({dim} {width}), expected at least 1")
    if (scenes.appearance_basis is None) != (scenes.appearance_proto is None):
        raise ValueError(f"{source}: fields 'appearance_basis' and 'appearance_proto' "
                         "must both be present (synthetic codes) or both absent")
    d = None if scenes.appearance_basis is None else scenes.appearance_basis.shape[-1]
    bases = {"global_basis": (scenes.global_feat.shape[-1], "G"),   # (rows, columns)
             "appearance_basis": (scenes.appearance.shape[-1], "d"),
             "appearance_proto": (C, d)}
    for name, (rows, cols) in bases.items():
        value = getattr(scenes, name)
        if value is not None and (value.ndim != 2 or value.shape[0] != rows
                                  or isinstance(cols, int) and value.shape[1] != cols):
            raise ValueError(f"{source}: field {name!r} has shape {tuple(value.shape)}, "
                             f"expected ({rows}, {cols})")
    for feat, scale_name in SCALE_OF.items():
        arr, scale = getattr(scenes, feat), getattr(scenes, scale_name)
        quantized = np.dtype(arr.dtype) == np.int8
        if quantized and scale is None:
            raise ValueError(f"{source}: field {feat!r} is int8 but field {scale_name!r} "
                             "(its per-channel dequantization scale) is missing")
        if not quantized and scale is not None:
            raise ValueError(f"{source}: field {scale_name!r} is given but {feat!r} is "
                             f"{arr.dtype}; the scale goes only with int8 features")
        if scale is not None and tuple(scale.shape) != (arr.shape[-1],):
            raise _shape_error(source, scale_name, scale.shape, f"({arr.shape[-1]},)")


def _nonfinite(block: np.ndarray) -> np.ndarray:
    """Bool mask of the NaN/Inf entries of a contiguous 1-D float block."""
    spec = _EXPONENT.get(block.dtype)
    if spec is None:
        return ~np.isfinite(block)
    utype, mask = spec
    return (block.view(utype) & utype(mask)) == utype(mask)


def _mapping(arr: np.ndarray):
    """(mmap, byte address of its start) when `arr` views a memory map, else None."""
    base = arr
    while base is not None and not isinstance(base, mmap.mmap):
        base = getattr(base, "base", None) if isinstance(base, np.ndarray) else None
    if base is None:
        return None
    start = np.frombuffer(base, np.uint8, count=1).ctypes.data if len(base) else 0
    return base, start


def release_pages(arr, lo: int = 0, hi: int | None = None) -> None:
    """Drop the resident pages of bytes lo..hi of a memory-mapped array from this
    process (madvise MADV_DONTNEED: the data stays in the page cache and is read back on
    the next access). No-op for arrays that are not read-only memory maps (a writable
    private map would lose its changes)."""
    arr = np.asarray(arr) if not isinstance(arr, np.ndarray) else arr
    if arr.flags.writeable or not hasattr(mmap, "MADV_DONTNEED"):
        return
    found = _mapping(arr)
    if found is None or arr.size == 0:
        return
    mm, start = found
    hi = arr.nbytes if hi is None else hi
    page = mmap.PAGESIZE
    a = arr.ctypes.data - start + lo
    b = arr.ctypes.data - start + hi
    a = (a + page - 1) // page * page        # only whole pages inside the range
    b = min(b, len(mm)) // page * page
    if b > a:
        try:
            mm.madvise(mmap.MADV_DONTNEED, a, b - a)
        except (OSError, ValueError):
            pass


def first_nonfinite(arr) -> tuple[tuple[int, ...], float] | None:
    """(index, value) of the first NaN/Inf of a float array, or None; reads the array
    in chunks of FINITE_CHUNK elements (a memory map is streamed, not loaded, and the
    pages read are released again)."""
    arr = np.asarray(arr) if not isinstance(arr, np.ndarray) else arr
    if arr.size == 0:
        return None
    flat = arr.reshape(-1)  # a view for C-contiguous arrays (np.load, memory maps)
    item = flat.dtype.itemsize
    for lo in range(0, flat.size, FINITE_CHUNK):
        block = np.ascontiguousarray(flat[lo:lo + FINITE_CHUNK])
        bad = _nonfinite(block)
        release_pages(flat, lo * item, (lo + block.size) * item)
        if bad.any():
            j = int(np.argmax(bad))
            return tuple(int(i) for i in np.unravel_index(lo + j, arr.shape)), float(block[j])
    return None


def first_outside(arr, lo: float, hi: float) -> tuple[tuple[int, ...], float] | None:
    """(index, value) of the first value of a (finite) array outside [lo, hi], or None;
    streamed in chunks like first_nonfinite."""
    arr = np.asarray(arr) if not isinstance(arr, np.ndarray) else arr
    if arr.size == 0:
        return None
    flat = arr.reshape(-1)
    item = flat.dtype.itemsize
    for start in range(0, flat.size, FINITE_CHUNK):
        block = np.asarray(flat[start:start + FINITE_CHUNK])
        bad = (block < lo) | (block > hi)
        release_pages(flat, start * item, (start + block.size) * item)
        if bad.any():
            j = int(np.argmax(bad))
            return (tuple(int(i) for i in np.unravel_index(start + j, arr.shape)),
                    float(block[j]))
    return None


def _scene(names: list[str], n: int) -> str:
    return f"scene {n} ({names[n]})" if 0 <= n < len(names) else f"scene {n}"


def _first(mask: np.ndarray) -> tuple[int, ...] | None:
    if not mask.any():
        return None
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(mask)), mask.shape))


def _action_name(a: int) -> str:
    return ACTIONS[a] if 0 <= a < NUM_ACTIONS else str(a)


def _check_ranges(scenes, source: str, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """state_count >= 1, the rooms' state ranges partition 0..T-1, room_type and split in
    range -> (offsets, counts) as int64."""
    T = scenes.next_state.shape[0]
    counts = np.asarray(scenes.state_count).astype(np.int64)
    offsets = np.asarray(scenes.state_offset).astype(np.int64)
    if counts.size and counts.min() < 1:
        n = int(np.argmax(counts < 1))
        raise ValueError(f"{source}: field 'state_count' is {counts[n]} for "
                         f"{_scene(names, n)}, expected >= 1")
    bad = (offsets < 0) | (offsets + counts > T)
    if bad.any():
        n = int(np.argmax(bad))
        raise ValueError(f"{source}: field 'state_offset' is {offsets[n]} for "
                         f"{_scene(names, n)} with state_count {counts[n]}: its states "
                         f"must lie in 0..{T - 1} (T = {T} flat states)")
    order = np.argsort(offsets, kind="stable")
    ends = np.cumsum(counts[order])
    starts = ends - counts[order]
    if (offsets[order] != starts).any() or (ends[-1] if ends.size else 0) != T:
        k = int(np.argmax(offsets[order] != starts)) if (offsets[order] != starts).any() \
            else len(order) - 1
        raise ValueError(f"{source}: fields 'state_offset' and 'state_count' must give every "
                         f"scene its own run of flat states, together exactly 0..{T - 1}; "
                         f"{_scene(names, int(order[k]))} starts at {offsets[order[k]]}, "
                         f"expected {starts[k]}")
    for name, limit, what in (("room_type", len(ROOM_TYPES), f"an index into {ROOM_TYPES}"),
                              ("split", len(SPLITS), "0 (train), 1 (val), 2 (test)")):
        arr = np.asarray(getattr(scenes, name))
        bad = (arr < 0) | (arr >= limit)
        if bad.any():
            n = int(np.argmax(bad))
            raise ValueError(f"{source}: field {name!r} is {arr[n]} for {_scene(names, n)}, "
                             f"expected {what}")
    return offsets, counts


def validate_values(scenes, source: str = "SceneSet") -> None:
    """The value checks of SceneSet.validate (shapes already checked):

    - dtypes: bool masks, integer indices, float features (int8 with a scale);
    - state_count >= 1 and the rooms' runs of flat states (state_offset, state_count)
      partition 0..T-1; room_type, split in range; next_state of every state is a state
      of its own scene;
    - every float field finite (pose, det_box, det_conf, float appearance and
      global_feat, the bases and scales if present), streamed in chunks; scales > 0;
      det_conf in [0, 1];
    - dist in 0..UNREACHABLE, expert_action in NO_ACTION..DONE, and the expert tables of
      expert.py: dist 0 exactly where the category is visible; Done exactly where
      dist is 0; NO_ACTION exactly where dist is UNREACHABLE; elsewhere expert_action is
      a move (0..4, rotations and looks cost 1 like MoveAhead) whose successor has dist
      exactly one less; no move reaches a state more than one closer (dist is the
      shortest path, not just a path);
    - targets only where the category is present and some state has a finite dist.
    """
    fields = {f.name: getattr(scenes, f.name) for f in dataclasses.fields(scenes)
              if f.name != "info"}
    for kinds, field_names in _FIELD_KINDS.items():
        for name in field_names:
            value = fields[name]
            if value is None:
                continue
            kind = np.dtype(value.dtype).kind
            ok = (kind == "f" or np.dtype(value.dtype) == np.int8) if kinds == "fi" \
                else kind in kinds
            if not ok:
                raise ValueError(f"{source}: field {name!r} has dtype {value.dtype}, expected "
                                 f"{_KINDS[kinds]}")
    names = scenes.scene_names
    offsets, counts = _check_ranges(scenes, source, names)
    nxt = np.asarray(scenes.next_state)
    scene_of = scenes.state_scene
    lo, hi = offsets[scene_of][:, None], (offsets + counts)[scene_of][:, None]
    hit = _first((nxt < lo) | (nxt >= hi))
    if hit:
        t, a = hit
        n = int(scene_of[t])
        raise ValueError(f"{source}: field 'next_state' holds {nxt[t, a]} at "
                         f"{_scene(names, n)} state {t - offsets[n]} action "
                         f"{_action_name(a)}; expected a state of that scene (flat indices "
                         f"{offsets[n]}..{offsets[n] + counts[n] - 1})")
    del lo, hi

    for name in _FIELD_KINDS["f"] + _FIELD_KINDS["fi"]:
        value = fields[name]
        if value is None or np.dtype(value.dtype).kind != "f":
            continue
        found = first_nonfinite(value)
        if found is not None:
            index, v = found
            v = "NaN" if np.isnan(v) else ("Inf" if v > 0 else "-Inf")
            if name == "appearance_proto":
                where = f"row {index[0]} ({CATEGORIES[index[0]]})"
            elif name in ("appearance_basis", "global_basis", "global_scale",
                          "appearance_scale"):
                where = f"index {index}"
            else:
                n = int(scene_of[index[0]])
                where = f"{_scene(names, n)} state {index[0] - offsets[n]}"
                if name in _CATEGORY_AXIS_FIELDS and len(index) > 1:
                    where += f" category {CATEGORIES[index[1]]}"
            raise ValueError(f"{source}: field {name!r} holds {v} at {where}; expected "
                             "finite values (the data is corrupt: rebuild or re-import it)")
    # the ranges the format promises beyond finiteness: a detection's confidence
    conf = fields["det_conf"]
    found = first_outside(conf, 0.0, 1.0)
    if found is not None:
        index, v = found
        n = int(scene_of[index[0]])
        raise ValueError(f"{source}: field 'det_conf' holds {v:g} at {_scene(names, n)} state "
                         f"{index[0] - offsets[n]} category {CATEGORIES[index[1]]}; expected "
                         "detection confidences in [0, 1] (0: no detection)")
    for name in SCALE_OF.values():
        scale = fields[name]
        if scale is not None and not (np.asarray(scale) > 0).all():
            raise ValueError(f"{source}: field {name!r} holds values <= 0; expected positive "
                             "per-channel scales")

    targets, present = np.asarray(scenes.targets), np.asarray(scenes.present)
    C = NUM_CATEGORIES
    for n in range(len(counts)):
        o, k = int(offsets[n]), int(counts[n])
        d = np.asarray(scenes.dist[o:o + k]).astype(np.int32)          # (k, C)
        a = np.asarray(scenes.expert_action[o:o + k]).astype(np.int32)  # (k, C)
        vis = np.asarray(scenes.visible[o:o + k])
        step = nxt[o:o + k] - o                                         # (k, A) local

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
