"""Detections, the global ray-cast code, and decoding features inside jit."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import scenes
from orgnav_jax.scenes.synthetic import detector, geometry, global_view, layout

GLOBAL_CH = {"floor": 0, "wall": 1, "furniture": 2, "object": 3, "ceiling": 4, "depth": 5}


@pytest.fixture(scope="module")
def dev(tiny_scenes):
    return tiny_scenes.to_device()


def _random_states(s: scenes.SceneSet, k: int, seed: int = 0):
    """k random states as global flat indices (a random scene, a random local state)."""
    rng = np.random.default_rng(seed)
    counts = np.asarray(s.state_count)
    n = rng.integers(0, s.num_scenes, k)
    st = (rng.random(k) * counts[n]).astype(np.int64)
    return np.asarray(s.global_state(n, st))


# ------------------------------------------------------------- gather_features
def test_gather_features_shapes(dev, tiny_scenes):
    preset = scenes.get_preset("tiny")
    assert tiny_scenes.global_dim == preset.global_dim
    assert tiny_scenes.appearance_dim == preset.appearance_dim
    idx = _random_states(tiny_scenes, 6)
    glob, app, box, conf = scenes.gather_features(dev, jnp.asarray(idx.reshape(2, 3)))
    G, d, C = preset.global_dim, preset.appearance_dim, K.NUM_CATEGORIES
    assert glob.shape == (2, 3, K.FEATURE_GRID, K.FEATURE_GRID, G)
    assert app.shape == (2, 3, C, d)
    assert box.shape == (2, 3, C, 4)
    assert conf.shape == (2, 3, C)
    for x in (glob, app, box, conf):
        assert x.dtype == jnp.float32
        assert bool(jnp.isfinite(x).all())


def test_gather_features_matches_numpy_reference(dev, tiny_scenes):
    s = tiny_scenes
    idx = _random_states(s, 64, seed=1)
    glob, app, box, conf = scenes.gather_features(dev, jnp.asarray(idx))
    code_g = np.asarray(s.global_feat)[idx].astype(np.float32)
    want_g = np.maximum(code_g @ np.asarray(s.global_basis), 0)
    np.testing.assert_allclose(np.asarray(glob), want_g, rtol=1e-4, atol=1e-4)
    c = np.asarray(s.det_conf)[idx].astype(np.float32)
    code_a = np.asarray(s.appearance)[idx].astype(np.float32)
    want_a = np.maximum(np.asarray(s.appearance_proto) + code_a @ np.asarray(s.appearance_basis), 0)
    want_a = np.where((c > 0)[..., None], want_a, 0)
    np.testing.assert_allclose(np.asarray(app), want_a, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(conf), c)
    np.testing.assert_array_equal(np.asarray(box),
                                  np.asarray(s.det_box)[idx].astype(np.float32))


def test_appearance_zero_exactly_where_nothing_detected(dev, tiny_scenes):
    idx = _random_states(tiny_scenes, 2000, seed=2)
    _, app, _, conf = scenes.gather_features(dev, jnp.asarray(idx))
    app, conf = np.asarray(app), np.asarray(conf)
    assert (app[conf == 0] == 0).all()
    assert (conf > 0).sum() > 50
    # where something is detected the feature carries information (almost never all 0)
    nonzero = np.abs(app[conf > 0]).sum(-1) > 0
    assert nonzero.mean() > 0.95


def test_jit_equals_eager_and_traces_once(dev, tiny_scenes):
    fn = jax.jit(chex.assert_max_traces(scenes.gather_features, n=1))
    for seed in (3, 4):
        idx = jnp.asarray(_random_states(tiny_scenes, 32, seed=seed))
        got = fn(dev, idx)
        want = scenes.gather_features(dev, idx)
        for g, w in zip(got, want):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-5, atol=1e-5)


def test_features_without_bases_are_the_stored_arrays(tiny_scenes):
    raw = tiny_scenes.replace(global_basis=None, appearance_basis=None, appearance_proto=None)
    assert raw.global_dim == tiny_scenes.global_feat.shape[-1]
    assert raw.appearance_dim == tiny_scenes.appearance.shape[-1]
    idx = _random_states(tiny_scenes, 8, seed=5)
    glob, app, _, _ = scenes.gather_features(raw, jnp.asarray(idx))
    np.testing.assert_array_equal(np.asarray(glob),
                                  np.asarray(tiny_scenes.global_feat)[idx].astype(np.float32))
    np.testing.assert_array_equal(np.asarray(app),
                                  np.asarray(tiny_scenes.appearance)[idx].astype(np.float32))


def test_to_device_keeps_everything(tiny_scenes, dev):
    assert dev.info == tiny_scenes.info
    for leaf in jax.tree_util.tree_leaves(dev):
        assert isinstance(leaf, jax.Array)
    assert dev.num_scenes == tiny_scenes.num_scenes


# ------------------------------------------------------------------ detections
def test_detection_arrays_well_formed(tiny_scenes):
    conf = np.asarray(tiny_scenes.det_conf).astype(np.float32)
    box = np.asarray(tiny_scenes.det_box).astype(np.float32)
    assert ((conf >= 0) & (conf <= 1)).all()
    assert ((box >= 0) & (box <= K.IMAGE_SIZE)).all()
    hit = conf > 0
    assert hit.any()
    assert (box[~hit] == 0).all()
    b = box[hit]
    assert (b[:, 0] <= b[:, 2]).all() and (b[:, 1] <= b[:, 3]).all()
    assert ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) > 0).mean() > 0.99
    # detections of categories absent from the room are rare false positives
    absent = ~np.asarray(tiny_scenes.present)[tiny_scenes.state_scene]     # (T, C)
    fp_rate = hit[absent].mean()
    assert fp_rate < 0.03
    assert (conf[hit & absent] <= 0.35 + 1e-3).all()
    # a visible (close, unoccluded) category is usually detected
    vis = np.asarray(tiny_scenes.visible)
    assert hit[vis].mean() > 0.6


def _room_detections(room, seed, fp, **knobs):
    from orgnav_jax.scenes.synthetic import builder
    from orgnav_jax.scenes.synthetic.perception import Perception
    assert room.floorplan == fp
    cells = geometry.reachable_cells(room.reachable)
    return builder.room_detections(room, seed, cells, geometry.state_poses(cells),
                                   Perception(**knobs))


def test_detection_pipeline_matches_room_arrays():
    from orgnav_jax.scenes.synthetic import builder
    ra = builder.room_arrays(0, 402, "train")
    _, _, box, conf, code = _room_detections(layout.generate_room(0, 402), 0, 402)
    np.testing.assert_array_equal(ra.det_conf, conf)
    np.testing.assert_array_equal(ra.det_box, box)
    np.testing.assert_array_equal(ra.appearance, code)


def test_large_categories_detected_farther_than_small(sample_rooms):
    large, small = ("Fridge", "Television"), ("CellPhone", "RemoteControl")
    dists = {c: [] for c in large + small}
    for fp in (1, 2, 3, 201, 202, 203):
        room = sample_rooms[fp]
        seen, dist, _, conf, _ = _room_detections(room, 0, fp, false_positive_rate=0.0)
        for name in dists:
            c = K.category_index(name)
            ks = np.flatnonzero(room.obj_category == c)
            if len(ks) != 1:
                continue
            k = ks[0]
            hit = conf[:, c] > 0
            assert (seen[hit, k]).all()          # without false positives: seen only
            dists[name].extend(dist[hit, k])
    for name, d in dists.items():
        assert len(d) > 100, name
    p90 = {name: np.percentile(d, 90) for name, d in dists.items()}
    assert min(p90[c] for c in large) > 1.4 * max(p90[c] for c in small), p90
    assert max(np.max(dists[c]) for c in small) < min(np.max(dists[c]) for c in large), p90


def test_detector_recall_by_range():
    S, dists = 4000, (0.5, 3.0)
    cats = np.array([K.category_index(c) for c in ("Fridge", "CellPhone")])
    boxes = np.tile(np.array([100, 100, 200, 200], np.float32), (S, 2, 1))
    rates = {}
    for d in dists:
        seen = np.ones((S, 2), bool)
        dist = np.full((S, 2), d)
        _, conf, code = detector.detect(np.random.default_rng(0), seen, dist, boxes, cats)
        rates[d] = (conf[:, cats] > 0).mean(0)
    assert (rates[0.5] > 0.8).all()               # both found up close
    assert rates[3.0][0] > 0.8                    # the Fridge from 3 m
    assert rates[3.0][1] < 0.1                    # a CellPhone almost never
    # not seen (occluded / out of view) or a tiny box: only false positives
    _, conf, _ = detector.detect(np.random.default_rng(0), np.zeros((S, 2), bool),
                                 np.full((S, 2), 0.5), boxes, cats)
    assert (conf[:, cats] > 0).mean() < 0.03 and conf.max() <= 0.35 + 1e-6
    tiny_box = np.tile(np.array([100, 100, 101, 101], np.float32), (S, 2, 1))
    _, conf, _ = detector.detect(np.random.default_rng(0), np.ones((S, 2), bool),
                                 np.full((S, 2), 0.5), tiny_box, cats)
    assert (conf[:, cats] > 0).mean() < 0.03


def test_detector_code_zero_where_nothing_detected():
    S = 500
    cats = np.array([K.category_index(c) for c in ("Fridge", "CellPhone")])
    boxes = np.tile(np.array([100, 100, 200, 200], np.float32), (S, 2, 1))
    _, conf, code = detector.detect(np.random.default_rng(0), np.ones((S, 2), bool),
                                    np.full((S, 2), 3.0), boxes, cats)
    assert (conf == 0).any()
    assert (code[conf == 0] == 0).all()


def test_stored_appearance_zero_where_nothing_detected(tiny_scenes):
    conf = np.asarray(tiny_scenes.det_conf)
    app = np.asarray(tiny_scenes.appearance)
    assert (app[conf == 0] == 0).all()


# --------------------------------------------------------------- global codes
def test_global_code_wall_up_close_vs_open_floor(make_room):
    room = make_room((14, 14))                 # empty 3 x 3 m room
    cells = geometry.reachable_cells(room.reachable)
    codes = global_view.global_codes(room, cells)
    assert codes.shape == (len(cells) * 16, K.FEATURE_GRID, K.FEATURE_GRID,
                           global_view.GLOBAL_CODE_DIM)
    kinds = codes[..., :5]
    np.testing.assert_allclose(kinds.sum(-1), 1.0)     # one-hot of what was hit
    m = {tuple(map(int, c)): i for i, c in enumerate(cells)}[(1, 6)]   # next to wall row 0

    def code(heading, horizon):
        return codes[m * 16 + (heading // 45) * 2 + K.HORIZONS.index(horizon)]

    wall_close, open_view = code(180, 0), code(0, 0)  # facing the wall / the open room
    assert wall_close[..., GLOBAL_CH["wall"]].sum() > open_view[..., GLOBAL_CH["wall"]].sum() + 10
    assert wall_close[..., GLOBAL_CH["wall"]].mean() > 0.8
    assert wall_close[..., GLOBAL_CH["depth"]].mean() < open_view[..., GLOBAL_CH["depth"]].mean()
    # open view at horizon 0: floor in the bottom row, not in the top row; ceiling on top
    # (the outer columns of the bottom row may reach the side walls first)
    assert open_view[-1, 2:5, GLOBAL_CH["floor"]].all()
    assert not open_view[0, :, GLOBAL_CH["floor"]].any()
    assert open_view[0, 2:5, GLOBAL_CH["ceiling"]].any() or open_view[0, 2:5, GLOBAL_CH["wall"]].all()
    # looking down shows more floor
    assert code(0, 30)[..., GLOBAL_CH["floor"]].sum() > open_view[..., GLOBAL_CH["floor"]].sum()
    # nothing but floor, wall and ceiling in an empty room
    assert codes[..., [GLOBAL_CH["furniture"], GLOBAL_CH["object"]]].sum() == 0
    assert (codes[..., 6:] == 0).all()


def test_global_code_sees_furniture(make_room):
    room = make_room((14, 14), furniture={(3, 5): 0.9, (3, 6): 0.9, (3, 7): 0.9})
    cells = geometry.reachable_cells(room.reachable)
    codes = global_view.global_codes(room, cells)
    m = {tuple(map(int, c)): i for i, c in enumerate(cells)}[(2, 6)]
    facing = codes[m * 16 + 0 * 2 + 1]        # heading 0 (towards the table), looking down
    assert facing[..., GLOBAL_CH["furniture"]].sum() > 0
    assert np.abs(facing[..., 6:9]).sum() > 0     # the furniture-kind embedding
    away = codes[m * 16 + 4 * 2 + 1]
    assert away[..., GLOBAL_CH["furniture"]].sum() == 0


def test_stored_global_codes_follow_state_order(tiny_scenes):
    """In the built set, states whose next cell ahead is a wall see more wall than states
    with at least three free cells ahead (checks code <-> state alignment)."""
    g = np.asarray(tiny_scenes.global_feat)
    ids = np.asarray(tiny_scenes.scene_id).tolist()
    for sid in (401, 301, 1):
        n = ids.index(sid)
        room = layout.generate_room(tiny_scenes.meta("seed"), sid)
        cells = geometry.reachable_cells(room.reachable)
        poses = geometry.state_poses(cells)
        rows = tiny_scenes.state_slice(n)
        assert rows.stop - rows.start == len(poses)
        np.testing.assert_allclose(np.asarray(tiny_scenes.pose)[rows], poses)
        close, far = [], []
        for s in range(0, len(poses), 2):     # horizon 0 only
            i, j = cells[s // 16]
            di, dj = geometry.HEADING_STEP[(s // 2) % 8]
            ahead = [(i + k * di, j + k * dj) for k in (1, 2, 3)]
            if room.wall[ahead[0]]:
                close.append(s)
            elif all(0 <= a < room.wall.shape[0] and 0 <= b < room.wall.shape[1]
                     and room.reachable[a, b] for a, b in ahead):
                far.append(s)
        assert len(close) > 5 and len(far) > 5, sid
        close, far = rows.start + np.asarray(close), rows.start + np.asarray(far)  # flat
        wall_close = g[close, ..., GLOBAL_CH["wall"]].astype(np.float32).mean()
        wall_far = g[far, ..., GLOBAL_CH["wall"]].astype(np.float32).mean()
        depth_close = g[close, ..., GLOBAL_CH["depth"]].astype(np.float32).mean()
        depth_far = g[far, ..., GLOBAL_CH["depth"]].astype(np.float32).mean()
        assert wall_close > wall_far + 0.2, (sid, wall_close, wall_far)
        assert depth_close < depth_far, (sid, depth_close, depth_far)


def test_global_code_left_right_matches_camera(make_room):
    """The ray caster and the pinhole camera agree on handedness: facing +z, +x is on
    the right of the image; facing -z it is on the left."""
    room = make_room((30, 14))                 # a long 3 x 7 m room
    cells = geometry.reachable_cells(room.reachable)
    codes = global_view.global_codes(room, cells)
    index = {tuple(map(int, c)): i for i, c in enumerate(cells)}
    wall = GLOBAL_CH["wall"]
    # next to the +x wall (column 13), facing +z along it: wall on the right
    c = codes[index[(3, 12)] * 16 + 0 * 2 + 0]
    assert c[:, 4:, wall].sum() > c[:, :3, wall].sum() + 10
    # at the far end, facing -z along the same wall: wall on the left
    c = codes[index[(26, 12)] * 16 + 4 * 2 + 0]
    assert c[:, :3, wall].sum() > c[:, 4:, wall].sum() + 10
    # the pinhole camera puts a point on the +x side to the right when facing +z
    poses = geometry.state_poses(np.array([[3, 6]]))           # x = 1.5, z = 0.75
    cam = geometry.to_camera(poses[[0, 8]], np.array([[2.5, 1.0, 2.0], [2.5, 1.0, -0.5]]))
    assert cam[0, 0, 0] > 0 and cam[0, 0, 2] > 0     # heading 0: ahead, to the right
    assert cam[1, 1, 0] < 0 and cam[1, 1, 2] > 0     # heading 180: ahead, to the left
