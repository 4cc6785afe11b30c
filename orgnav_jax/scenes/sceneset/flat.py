"""The flat (unpadded) SceneSet layout: building it, expert tables on it, padding it back.

    dist, action = flat_expert_tables(next_state, visible, offsets, counts)
    scenes = from_padded(arrays)          # padded per-room arrays (format 1) -> SceneSet
    padded = to_padded(scenes, "dist", fill=UNREACHABLE)   # (N, S_max, ...) for tools/tests

from_padded is the one place that turns the old padded layout (N, S, ...) with a
`state_valid` mask into the flat one (storage.load of format-1 sets, `python -m
orgnav_jax.scenes convert`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from orgnav_jax.constants import NUM_ACTIONS
from orgnav_jax.scenes.sceneset.expert import expert_tables
from orgnav_jax.scenes.sceneset.fields import NO_ACTION, PER_STATE_FIELDS, UNREACHABLE
from orgnav_jax.scenes.sceneset.sceneset import SceneSet, storage_offsets

EXPERT_CHUNK = 8  # rooms per expert-table call (bounds memory; one compile)


def flat_expert_tables(next_state, visible, offsets, counts, chunk: int = EXPERT_CHUNK,
                       pad_to: int | None = None):
    """Expert tables of flat rooms: next_state (T, A) global indices, visible (T, C),
    offsets, counts (N,) -> dist (T, C) int16, expert_action (T, C) int8.

    Rooms go through expert.expert_tables `chunk` at a time, each padded to
    pad_to (default: the largest room) states that lead to themselves and see nothing,
    so every call has one shape (one compile) and memory stays bounded."""
    next_state, visible = np.asarray(next_state), np.asarray(visible)
    offsets = np.asarray(offsets).astype(np.int64)
    counts = np.asarray(counts).astype(np.int64)
    T, C = visible.shape
    N, S = len(counts), int(pad_to or counts.max())
    dist = np.full((T, C), UNREACHABLE, np.int16)
    action = np.full((T, C), NO_ACTION, np.int8)
    for lo in range(0, N, chunk):
        idx = np.arange(lo, lo + chunk) % N  # pad the last chunk: one compile
        nxt = np.tile(np.arange(S, dtype=np.int32)[None, :, None], (chunk, 1, NUM_ACTIONS))
        vis = np.zeros((chunk, S, C), bool)
        valid = np.zeros((chunk, S), bool)
        for j, n in enumerate(idx):
            o, k = offsets[n], counts[n]
            nxt[j, :k] = next_state[o:o + k] - o
            vis[j, :k] = visible[o:o + k]
            valid[j, :k] = True
        d, a = expert_tables(jnp.asarray(nxt), jnp.asarray(vis), jnp.asarray(valid))
        d, a = np.asarray(d), np.asarray(a)
        for j, n in enumerate(idx[:min(chunk, N - lo)]):
            o, k = offsets[n], counts[n]
            dist[o:o + k], action[o:o + k] = d[j, :k], a[j, :k]
    return dist, action


def from_padded(arrays: dict, info: tuple = ()) -> SceneSet:
    """A SceneSet from the padded layout of format 1: per-state fields (N, S, ...) with
    next_state in per-room indices and the `state_valid` (N, S) mask (valid states first
    in each room), per-scene fields (N, ...), optional bases. Only the valid rows are
    copied, grouped by split (sceneset.storage_offsets)."""
    arrays = dict(arrays)
    valid = np.asarray(arrays.pop("state_valid"))
    counts = valid.sum(1).astype(np.int32)
    if "state_count" in arrays and not np.array_equal(np.asarray(arrays["state_count"]),
                                                      counts):
        raise ValueError("field 'state_count' disagrees with 'state_valid' (padded layout)")
    arrays.pop("state_count", None)
    split = np.asarray(arrays["split"])
    offsets = storage_offsets(split, counts)
    order = np.argsort(offsets, kind="stable")
    out = {}
    for name in PER_STATE_FIELDS:
        padded = arrays.pop(name)
        rows = [np.asarray(padded[n, :counts[n]]) for n in order]
        if name == "next_state":
            rows = [r.astype(np.int32) + offsets[n] for r, n in zip(rows, order)]
        out[name] = np.concatenate(rows)
    return SceneSet(**out, **arrays, state_offset=offsets, state_count=counts, info=info)


def to_padded(scenes: SceneSet, name: str, fill=0) -> np.ndarray:
    """A per-state field in the padded layout (N, S_max, ...), `fill` beyond each room's
    states; next_state in per-room (local) indices, padding states leading to
    themselves. For tools and tests that compare against the padded layout."""
    arr = np.asarray(getattr(scenes, name))
    offsets, counts = np.asarray(scenes.state_offset), np.asarray(scenes.state_count)
    N, S = scenes.num_scenes, scenes.max_states
    if name == "next_state":
        out = np.tile(np.arange(S, dtype=arr.dtype)[None, :, None], (N, 1, arr.shape[-1]))
    else:
        out = np.full((N, S) + arr.shape[1:], fill, arr.dtype)
    for n in range(N):
        o, k = int(offsets[n]), int(counts[n])
        out[n, :k] = arr[o:o + k] - (o if name == "next_state" else 0)
    return out


def padded_valid(scenes: SceneSet) -> np.ndarray:
    """(N, S_max) bool: True on each room's states (the old `state_valid`)."""
    counts = np.asarray(scenes.state_count)
    return np.arange(scenes.max_states)[None] < counts[:, None]
