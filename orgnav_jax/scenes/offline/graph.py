"""State order and transitions of an imported scene, recovered from poses alone.

The authors' graph.json has unlabelled edges; the action of an edge u -> v is the one
whose successor pose (constants.HEADING_STEP, rotation +-45, horizon 30 <-> 0) is v.
Positions (x, z) in metres, possibly negative, map to grid cells
row = round((z - z_min) / 0.25), col = round((x - x_min) / 0.25).
"""

from __future__ import annotations

import numpy as np

from orgnav_jax.constants import (
    GRID_SIZE, HEADING_STEP, HORIZONS, LOOK_DOWN, LOOK_UP, MOVE_AHEAD, NUM_ACTIONS,
    NUM_HEADINGS, ROTATE_LEFT, ROTATE_RIGHT, ROTATION_STEP,
)
from orgnav_jax.scenes.offline.validate import OfflineFormatError, examples

OFF_GRID_TOLERANCE = 0.2  # cells: |(x - x_min) / 0.25 - col| above this is not on the grid


def grid_states(pose: np.ndarray, keys: list[str], source: str) -> np.ndarray:
    """(S, 4) poses -> (S, 4) int64 grid states (row, col, heading 0..7, horizon index 0/1).

    Raises if a position is off the 0.25 m grid or two keys land on one grid state."""
    out = np.empty((len(pose), 4), np.int64)
    for axis, (col, name) in enumerate(((1, "z"), (0, "x"))):
        value = pose[:, col]
        cell = (value - value.min()) / GRID_SIZE
        out[:, axis] = np.rint(cell)
        off = np.abs(cell - out[:, axis]) > OFF_GRID_TOLERANCE
        if off.any():
            bad = [keys[i] for i in np.flatnonzero(off)]
            raise OfflineFormatError(f"{source}: {len(bad)} state(s) with {name} off the "
                                     f"{GRID_SIZE} m grid: {examples(bad)}")
    out[:, 2] = np.rint(pose[:, 2] / ROTATION_STEP).astype(np.int64) % NUM_HEADINGS
    out[:, 3] = np.searchsorted(np.asarray(HORIZONS), np.rint(pose[:, 3]))
    flat = np.ravel_multi_index(out.T, (out[:, 0].max() + 1, out[:, 1].max() + 1,
                                        NUM_HEADINGS, len(HORIZONS)))
    _, first, counts = np.unique(flat, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = flat[first[counts > 1][0]]
        same = [keys[i] for i in np.flatnonzero(flat == dup)]
        raise OfflineFormatError(f"{source}: state keys {examples(same)} fall on the same "
                                 "grid state (positions closer than the 0.25 m grid)")
    return out


def state_order(grid: np.ndarray) -> np.ndarray:
    """(S, 4) grid states -> (S,) permutation sorting by row, col, heading, horizon (the
    synthetic builder's order: cells row-major, then 16 views per cell)."""
    return np.lexsort((grid[:, 3], grid[:, 2], grid[:, 1], grid[:, 0]))


def edge_actions(grid: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(S, 4) grid states, (E,) source and target indices -> (E,) action index, or -1
    where the pose change matches no action (self-links included)."""
    a, b = grid[src], grid[dst]
    d_row, d_col = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    d_head = (b[:, 2] - a[:, 2]) % NUM_HEADINGS
    same_cell = (d_row == 0) & (d_col == 0)
    same_view = (d_head == 0) & (b[:, 3] == a[:, 3])
    step = np.array(HEADING_STEP)[a[:, 2]]
    out = np.full(len(src), -1, np.int64)
    move = same_view & (d_row == step[:, 0]) & (d_col == step[:, 1])
    out[move] = MOVE_AHEAD
    level = same_cell & (b[:, 3] == a[:, 3])
    out[level & (d_head == NUM_HEADINGS - 1)] = ROTATE_LEFT
    out[level & (d_head == 1)] = ROTATE_RIGHT
    turn = same_cell & (d_head == 0)
    out[turn & (a[:, 3] == 1) & (b[:, 3] == 0)] = LOOK_UP
    out[turn & (a[:, 3] == 0) & (b[:, 3] == 1)] = LOOK_DOWN
    return out


def transitions(grid: np.ndarray, src: np.ndarray, dst: np.ndarray, keys: list[str],
                source: str, directed: bool = True, unmatched: str = "error"
                ) -> tuple[np.ndarray, int]:
    """Edges -> ((S, A) int32 next_state, number of edges ignored).

    Actions without an edge fail (stay put); Done stays. For an undirected graph both
    directions of each link are tried (the reverse of a MoveAhead matches nothing and
    is dropped). An edge matching no action is an error, or with unmatched='ignore'
    dropped and counted. Self-links are always dropped (not an action)."""
    S = len(grid)
    if not directed:
        src, dst = np.concatenate([src, dst]), np.concatenate([dst, src])
    act = edge_actions(grid, src, dst)
    bad = (act < 0) & (src != dst)
    if not directed:  # a link is bad only if neither direction matched an action
        half = len(act) // 2
        bad = bad[:half] & bad[half:]
    if bad.any() and unmatched == "error":
        pairs = [f"{keys[s]} -> {keys[t]}"
                 for s, t in zip(src[:len(bad)][bad], dst[:len(bad)][bad])]
        raise OfflineFormatError(
            f"{source}: {len(pairs)} edge(s) match no action (MoveAhead one 0.25 m step along "
            f"the heading, RotateLeft/Right +-45 deg, LookUp 30->0, LookDown 0->30): "
            f"{examples(pairs)}")
    nxt = np.tile(np.arange(S, dtype=np.int32)[:, None], (1, NUM_ACTIONS))
    ok = act >= 0
    nxt[src[ok], act[ok]] = dst[ok]
    return nxt, int(bad.sum())
