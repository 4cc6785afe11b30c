"""Camera model, line of sight and visibility on small hand-made rooms."""

from __future__ import annotations

import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax.scenes.synthetic import detector, geometry

SHAPE = (12, 9)          # rows 0..11 (z = 0 .. 2.75 m), cols 0..8 (x = 0 .. 2 m)
AGENT = (2, 4)           # x = 1.0 m, z = 0.5 m
X0, Z0 = AGENT[1] * K.GRID_SIZE, AGENT[0] * K.GRID_SIZE
BOWL = K.category_index("Bowl")


def observe(room):
    """Everything per state for a room: (index, seen, dist, los, visible, cam)."""
    cells = geometry.reachable_cells(room.reachable)
    poses = geometry.state_poses(cells)
    los = geometry.line_of_sight(room.block_height, cells, room.obj_center, room.obj_size,
                                 detector.MAX_DETECT_DISTANCE)
    seen, dist, cam = geometry.object_visibility(poses, cells, los, room.obj_center)
    visible = geometry.category_visible(seen, dist, room.obj_category, K.NUM_CATEGORIES)
    index = {tuple(map(int, c)): m for m, c in enumerate(cells)}
    return dict(index=index, seen=seen, dist=dist, los=los, visible=visible, cam=cam,
                poses=poses, cells=cells)


def sid(obs, cell, heading, horizon):
    return obs["index"][cell] * 16 + (heading // 45) * 2 + K.HORIZONS.index(horizon)


def test_object_ahead_visible_only_when_facing_it(make_room):
    room = make_room(SHAPE, objects=[("Bowl", X0, 0.9, Z0 + 1.0)])
    obs = observe(room)
    for horizon in K.HORIZONS:
        s = sid(obs, AGENT, 0, horizon)
        assert obs["seen"][s, 0]
        assert obs["dist"][s, 0] == pytest.approx(1.0, abs=1e-5)
        assert obs["visible"][s, BOWL]
        for away in (90, 135, 180, 225, 270):
            s = sid(obs, AGENT, away, horizon)
            assert not obs["seen"][s, 0], away
            assert not obs["visible"][s, BOWL], away
    # only the category of the object is ever visible
    other = np.delete(obs["visible"], BOWL, axis=1)
    assert not other.any()
    assert obs["visible"][:, BOWL].any()


def test_visibility_needs_distance_within_1_5_m(make_room):
    room = make_room(SHAPE, objects=[("Bowl", X0, 0.9, Z0 + 2.0)])
    obs = observe(room)
    for horizon in K.HORIZONS:
        s = sid(obs, AGENT, 0, horizon)
        assert obs["dist"][s, 0] == pytest.approx(2.0, abs=1e-5)
        assert obs["los"][obs["index"][AGENT], 0]
        assert obs["seen"][s, 0]            # in view and unoccluded ...
        assert not obs["visible"][s, BOWL]  # ... but farther than 1.5 m
    # walking towards it along the column: visible exactly once within 1.5 m
    for i in range(1, 10):
        s = sid(obs, (i, 4), 0, 30)
        d = Z0 + 2.0 - i * K.GRID_SIZE
        assert obs["visible"][s, BOWL] == (0 < d <= K.VISIBILITY_DISTANCE + 1e-6), i


@pytest.mark.parametrize("blocker", ["wall", "shelf"])
def test_wall_or_tall_furniture_blocks_line_of_sight(make_room, blocker):
    obj = ("Bowl", X0, 0.75 + 0.04, Z0 + 1.0)   # on a table 1 m ahead
    table = {(6, 4): 0.75}
    if blocker == "wall":
        room = make_room(SHAPE, walls=[(4, 4)], furniture=table, objects=[obj])
    else:
        room = make_room(SHAPE, furniture={**table, (4, 4): 1.80}, objects=[obj])
    obs = observe(room)
    m = obs["index"][AGENT]
    assert not obs["los"][m, 0]
    for horizon in K.HORIZONS:
        s = sid(obs, AGENT, 0, horizon)
        assert not obs["seen"][s, 0]
        assert not obs["visible"][s, BOWL]
    # from the side, with a clear line, the same object is visible
    s = sid(obs, (6, 2), 90, 30)
    assert obs["los"][obs["index"][(6, 2)], 0]
    assert obs["visible"][s, BOWL]


def test_low_furniture_does_not_block(make_room):
    obj = ("Bowl", X0, 0.75 + 0.04, Z0 + 1.0)
    room = make_room(SHAPE, furniture={(6, 4): 0.75, (4, 4): 0.45}, objects=[obj])
    obs = observe(room)
    assert obs["los"][obs["index"][AGENT], 0]
    for horizon in K.HORIZONS:
        assert obs["visible"][sid(obs, AGENT, 0, horizon), BOWL]


def test_floor_object_close_needs_look_down(make_room):
    room = make_room(SHAPE, unreachable=[(4, 4)],
                     objects=[("GarbageCan", X0, 0.2, Z0 + 0.5)])
    obs = observe(room)
    can = K.category_index("GarbageCan")
    s0, s30 = sid(obs, AGENT, 0, 0), sid(obs, AGENT, 0, 30)
    assert obs["los"][obs["index"][AGENT], 0]
    assert not obs["seen"][s0, 0] and not obs["visible"][s0, can]
    assert obs["seen"][s30, 0] and obs["visible"][s30, can]


def test_wall_mounted_object_not_hidden_by_its_wall(make_room):
    # a LightSwitch placed like the generator does: 0.6 of a cell off the wall cell
    z = (SHAPE[0] - 1 - 0.6) * K.GRID_SIZE
    room = make_room(SHAPE, objects=[("LightSwitch", X0, 1.3, z)])
    obs = observe(room)
    s = sid(obs, (7, 4), 0, 0)
    assert obs["los"][obs["index"][(7, 4)], 0]
    assert obs["visible"][s, K.category_index("LightSwitch")]


def test_full_height_wall_blocks_even_high_objects(make_room):
    room = make_room(SHAPE, walls=[(4, 3), (4, 4), (4, 5)],
                     objects=[("LightSwitch", X0, 2.2, Z0 + 1.0)])
    obs = observe(room)
    assert not obs["los"][obs["index"][AGENT], 0]


def test_camera_axes_and_image_orientation(make_room):
    # object 1 m ahead (+z) and 0.5 m to the +x side, below the eye
    room = make_room(SHAPE, objects=[("Bowl", X0 + 0.5, 0.9, Z0 + 1.0)])
    obs = observe(room)
    cam = obs["cam"]
    s = sid(obs, AGENT, 0, 0)
    # facing +z, +x is to the right; the object is below the eye
    assert cam[s, 0, 0] == pytest.approx(0.5, abs=1e-5)
    assert cam[s, 0, 1] == pytest.approx(0.9 - K.CAMERA_HEIGHT, abs=1e-5)
    assert cam[s, 0, 2] == pytest.approx(1.0, abs=1e-5)
    # facing +x (90 deg), the same object is ahead and to the left
    s90 = sid(obs, AGENT, 90, 0)
    assert cam[s90, 0, 2] == pytest.approx(0.5, abs=1e-5)
    assert cam[s90, 0, 0] == pytest.approx(-1.0, abs=1e-5)
    boxes = detector.project_boxes(obs["poses"], room.obj_center, room.obj_size,
                                   room.obj_height)
    cx = (boxes[:, 0, 0] + boxes[:, 0, 2]) / 2
    cy = (boxes[:, 0, 1] + boxes[:, 0, 3]) / 2
    assert cx[s] > K.IMAGE_SIZE / 2      # right half of the image
    assert cy[s] > K.IMAGE_SIZE / 2      # below the centre
    # looking down moves the object up in the image
    assert cy[sid(obs, AGENT, 0, 30)] < cy[s]
    # the box is a proper box inside the image
    b = boxes[s, 0]
    assert 0 <= b[0] < b[2] <= K.IMAGE_SIZE and 0 <= b[1] < b[3] <= K.IMAGE_SIZE


def test_field_of_view_is_90_degrees():
    poses = np.array([[0.0, 0.0, 0.0, 0.0]], np.float32)   # at origin, facing +z, level
    eye = K.CAMERA_HEIGHT
    pts = np.array([
        [0.9, eye, 1.0],    # 42 deg right: in view
        [1.1, eye, 1.0],    # 48 deg right: out
        [-0.9, eye, 1.0],   # 42 deg left: in view
        [0.0, eye - 0.9, 1.0],  # 42 deg down: in view
        [0.0, eye - 1.1, 1.0],  # 48 deg down: out at horizon 0
        [0.0, eye, -1.0],   # behind
    ], np.float32)
    inside = geometry.in_view(geometry.to_camera(poses, pts))[0]
    np.testing.assert_array_equal(inside, [True, False, True, True, False, False])
    down = np.array([[0.0, 0.0, 0.0, 30.0]], np.float32)
    assert geometry.in_view(geometry.to_camera(down, pts))[0, 4]


def test_category_visible_any_instance_within_range():
    # two instances of category 3 and one of 5, in three states
    seen = np.array([[True, False, True], [False, True, True], [True, True, False]])
    dist = np.array([[2.0, 1.0, 1.0], [1.0, 1.4, 1.6], [1.5, 3.0, 0.5]])
    cats = np.array([3, 3, 5])
    out = geometry.category_visible(seen, dist, cats, K.NUM_CATEGORIES)
    assert out.shape == (3, K.NUM_CATEGORIES) and out.dtype == bool
    np.testing.assert_array_equal(out[:, 3], [False, True, True])
    np.testing.assert_array_equal(out[:, 5], [True, False, False])
    assert not np.delete(out, [3, 5], axis=1).any()


def test_generated_rooms_visible_only_present_categories(sample_rooms):
    for fp, room in list(sample_rooms.items())[::2]:
        obs = observe(room)
        present = np.zeros(K.NUM_CATEGORIES, bool)
        present[room.obj_category] = True
        assert not obs["visible"][:, ~present].any(), f"FloorPlan{fp}"
        # the LightSwitch by the door can be seen from somewhere
        assert obs["visible"][:, K.category_index("LightSwitch")].any(), f"FloorPlan{fp}"
