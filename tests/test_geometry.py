"""Movement rules (geometry.transitions) and state indexing (geometry.state_poses)."""

from __future__ import annotations

import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax.scenes.synthetic import geometry

SPC = geometry.STATES_PER_CELL  # 16

# The headings in degrees and the grid step (di, dj) the task defines for them:
# 0 deg -> +z = +1 row, 90 deg -> +x = +1 column; diagonals move both.
EXPECTED_STEP = {
    0: (1, 0), 45: (1, 1), 90: (0, 1), 135: (-1, 1),
    180: (-1, 0), 225: (-1, -1), 270: (0, -1), 315: (1, -1),
}


def _setup(room):
    cells = geometry.reachable_cells(room.reachable)
    index = {tuple(map(int, c)): m for m, c in enumerate(cells)}
    nxt = geometry.transitions(cells, room.wall.shape)
    return cells, index, nxt


def _state(index, cell, heading_deg, horizon_deg):
    h = heading_deg // K.ROTATION_STEP
    v = K.HORIZONS.index(horizon_deg)
    return index[cell] * SPC + h * 2 + v


def _decode(cells, s):
    m, h, v = s // SPC, (s // 2) % K.NUM_HEADINGS, s % 2
    return tuple(map(int, cells[m])), int(h * K.ROTATION_STEP), K.HORIZONS[v]


@pytest.fixture
def open_room(make_room):
    """9x9 grid, interior rows/cols 1..7. Furniture at (4, 6); free but unreachable
    cell (6, 6); an extra wall cell (2, 2)."""
    return make_room((9, 9), walls=[(2, 2)], furniture={(4, 6): 0.75}, unreachable=[(6, 6)])


@pytest.mark.parametrize("heading", sorted(EXPECTED_STEP))
@pytest.mark.parametrize("horizon", K.HORIZONS)
def test_move_ahead_all_headings(open_room, heading, horizon):
    cells, index, nxt = _setup(open_room)
    start = (4, 4)
    s = _state(index, start, heading, horizon)
    di, dj = EXPECTED_STEP[heading]
    target = (start[0] + di, start[1] + dj)
    assert _decode(cells, nxt[s, K.MOVE_AHEAD]) == (target, heading, horizon)


def test_heading_step_table_matches_convention():
    for h in range(K.NUM_HEADINGS):
        assert tuple(geometry.HEADING_STEP[h]) == EXPECTED_STEP[h * K.ROTATION_STEP]


@pytest.mark.parametrize("start,heading,why", [
    ((1, 1), 180, "outer wall (row 0)"),
    ((1, 1), 270, "outer wall (col 0)"),
    ((1, 1), 225, "outer wall corner"),
    ((7, 7), 0, "outer wall (row 8)"),
    ((7, 7), 45, "outer wall corner"),
    ((3, 2), 180, "inner wall cell (2, 2)"),
    ((1, 1), 45, "inner wall cell (2, 2) diagonally"),
    ((4, 5), 90, "furniture at (4, 6)"),
    ((3, 6), 0, "furniture at (4, 6) from below"),
    ((5, 5), 45, "free but unreachable cell (6, 6)"),
    ((6, 5), 90, "free but unreachable cell (6, 6)"),
])
@pytest.mark.parametrize("horizon", K.HORIZONS)
def test_move_ahead_blocked_stays_put(open_room, start, heading, why, horizon):
    cells, index, nxt = _setup(open_room)
    s = _state(index, start, heading, horizon)
    assert nxt[s, K.MOVE_AHEAD] == s, why


def test_unreachable_and_blocked_cells_have_no_states(open_room):
    cells, index, _ = _setup(open_room)
    for cell in [(2, 2), (4, 6), (6, 6), (0, 0), (8, 4)]:
        assert cell not in index
    assert len(cells) == int(open_room.reachable.sum())


def test_rotations_and_looks(open_room):
    cells, index, nxt = _setup(open_room)
    for cell in [(1, 1), (4, 4), (7, 7)]:
        for heading in EXPECTED_STEP:
            for horizon in K.HORIZONS:
                s = _state(index, cell, heading, horizon)
                assert _decode(cells, nxt[s, K.ROTATE_LEFT]) == (
                    cell, (heading - 45) % 360, horizon)
                assert _decode(cells, nxt[s, K.ROTATE_RIGHT]) == (
                    cell, (heading + 45) % 360, horizon)
                up = (cell, heading, 0)  # LookUp only from 30 (down) to 0; else stays
                down = (cell, heading, 30)  # LookDown only from 0 to 30; else stays
                assert _decode(cells, nxt[s, K.LOOK_UP]) == up
                assert _decode(cells, nxt[s, K.LOOK_DOWN]) == down
                assert (nxt[s, K.LOOK_UP] == s) == (horizon == 0)
                assert (nxt[s, K.LOOK_DOWN] == s) == (horizon == 30)
                assert nxt[s, K.DONE] == s


def test_eight_rotations_return_to_start(open_room):
    cells, index, nxt = _setup(open_room)
    s0 = _state(index, (4, 4), 90, 30)
    for action in (K.ROTATE_LEFT, K.ROTATE_RIGHT):
        s, seen = s0, set()
        for _ in range(K.NUM_HEADINGS):
            seen.add(int(s))
            s = nxt[s, action]
        assert s == s0 and len(seen) == K.NUM_HEADINGS


def test_state_poses_index_formula(open_room):
    cells = geometry.reachable_cells(open_room.reachable)
    poses = geometry.state_poses(cells)
    assert poses.shape == (len(cells) * SPC, 4) and poses.dtype == np.float32
    for m, (i, j) in enumerate(cells):
        for h in range(K.NUM_HEADINGS):
            for v in range(len(K.HORIZONS)):
                s = m * 16 + h * 2 + v
                np.testing.assert_allclose(
                    poses[s], [j * K.GRID_SIZE, i * K.GRID_SIZE, h * 45, K.HORIZONS[v]])


def test_reachable_cells_row_major(open_room):
    cells = geometry.reachable_cells(open_room.reachable)
    keys = [tuple(c) for c in cells]
    assert keys == sorted(keys)
    assert all(open_room.reachable[i, j] for i, j in keys)


def _reference_transitions(reachable: np.ndarray) -> np.ndarray:
    """Straightforward re-implementation of the movement rules, state by state."""
    cells = [tuple(map(int, c)) for c in np.argwhere(reachable)]
    index = {c: m for m, c in enumerate(cells)}
    out = np.zeros((len(cells) * SPC, K.NUM_ACTIONS), np.int64)
    for m, (i, j) in enumerate(cells):
        for h in range(K.NUM_HEADINGS):
            di, dj = EXPECTED_STEP[h * 45]
            for v in range(2):
                s = m * SPC + h * 2 + v
                tgt = index.get((i + di, j + dj))
                out[s, K.MOVE_AHEAD] = s if tgt is None else tgt * SPC + h * 2 + v
                out[s, K.ROTATE_LEFT] = m * SPC + ((h - 1) % 8) * 2 + v
                out[s, K.ROTATE_RIGHT] = m * SPC + ((h + 1) % 8) * 2 + v
                out[s, K.LOOK_UP] = m * SPC + h * 2 + 0
                out[s, K.LOOK_DOWN] = m * SPC + h * 2 + 1
                out[s, K.DONE] = s
    return out


def test_generated_rooms_match_reference_rules(sample_rooms):
    for fp, room in sample_rooms.items():
        cells = geometry.reachable_cells(room.reachable)
        nxt = geometry.transitions(cells, room.wall.shape)
        assert nxt.dtype == np.int32
        np.testing.assert_array_equal(nxt, _reference_transitions(room.reachable),
                                      err_msg=f"FloorPlan{fp}")


def test_generated_rooms_transitions_stay_valid(sample_rooms):
    for fp, room in sample_rooms.items():
        cells = geometry.reachable_cells(room.reachable)
        nxt = geometry.transitions(cells, room.wall.shape)
        assert nxt.min() >= 0 and nxt.max() < len(cells) * SPC, f"FloorPlan{fp}"
        # a successful MoveAhead lands on a reachable cell one step away
        moved = nxt[:, K.MOVE_AHEAD] != np.arange(len(nxt))
        src = cells[np.arange(len(nxt)) // SPC]
        dst = cells[nxt[:, K.MOVE_AHEAD] // SPC]
        step = np.abs(dst - src)
        assert (step[moved].max(1) == 1).all()
        assert (step[~moved] == 0).all()
        assert room.reachable[dst[:, 0], dst[:, 1]].all()
        # most states can move (rooms are not a maze of dead ends)
        assert moved.mean() > 0.5, f"FloorPlan{fp}"


def test_sceneset_transitions_stay_in_their_room(tiny_scenes):
    nxt = np.asarray(tiny_scenes.next_state)
    T, A = nxt.shape
    assert A == K.NUM_ACTIONS and T == int(np.asarray(tiny_scenes.state_count).sum())
    for n in range(tiny_scenes.num_scenes):
        rows = tiny_scenes.state_slice(n)
        s_n = rows.stop - rows.start
        assert s_n % SPC == 0
        # global flat indices, inside the room's own run of states
        assert (nxt[rows] < rows.stop).all() and (nxt[rows] >= rows.start).all()


def test_sceneset_states_strongly_connected(tiny_scenes):
    """Every valid state can reach every other (reachable cells are one component and
    moves can be undone by turning around)."""
    import networkx as nx
    nxt = np.asarray(tiny_scenes.next_state)
    for n in range(0, tiny_scenes.num_scenes, 3):
        rows = tiny_scenes.state_slice(n)
        s_n = rows.stop - rows.start
        g = nx.DiGraph()
        g.add_nodes_from(range(s_n))
        for a in range(K.DONE):
            g.add_edges_from(zip(range(s_n), (nxt[rows, a] - rows.start).tolist()))
        assert nx.is_strongly_connected(g), tiny_scenes.scene_names[n]
