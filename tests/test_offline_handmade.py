"""A tiny hand-written offline scene with known answers: transitions, visibility, path
lengths, expert actions, optimal_action.json comparison, features and padding.

The scene (FloorPlan401, a bathroom) is a 3 x 3 grid of points x in {-0.50, -0.25, 0.00},
z in {1.00, 1.25, 1.50} whose centre (-0.25, 1.25) is not reachable: 8 cells x 16 views.
Its graph is written here from an explicit table of moves, independently of the importer.
`write_scene` is also used by test_offline_errors.py.
"""

from __future__ import annotations

import json
import pickle

import h5py
import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax.scenes import NO_ACTION, UNREACHABLE
from orgnav_jax.scenes.sceneset.keys import key_index, state_key
from orgnav_jax.scenes.offline.episodes import load_offline_episodes
from orgnav_jax.scenes.offline import OfflineFormatError, import_offline

XS, ZS = (-0.50, -0.25, 0.00), (1.00, 1.25, 1.50)
BLOCKED = {(-0.25, 1.25)}
# MoveAhead displacement in grid steps (dx, dz) per rotation: 0 deg -> +z, 90 deg -> +x.
MOVE = {0: (0, 1), 45: (1, 1), 90: (1, 0), 135: (1, -1), 180: (0, -1), 225: (-1, -1),
        270: (-1, 0), 315: (-1, 1)}
G, D = 4, 3  # feature widths of the hand-made hdf5 files
SINK_ID = "Sink|+00.30|+00.90|+01.60|SinkBasin"
SINK_AT = ["0.00|1.50|90|0", "0.00|1.50|90|30"]
CAN_ID = "GarbageCan|-00.80|+00.20|+00.90"
CAN_AT = ["-0.50|1.00|225|30"]
START = "-0.50|1.00|0|0"


def key(x, z, rot, hor) -> str:
    return f"{x:.2f}|{z:.2f}|{rot}|{hor}"


def points(xs=XS, zs=ZS, blocked=BLOCKED):
    return [(x, z) for x in xs for z in zs if (x, z) not in blocked]


def states(pts):
    return [key(x, z, r, h) for x, z in pts for r in MOVE for h in (0, 30)]


def edges(pts):
    """Successful actions only, as the authors' BFS writes them."""
    cells = {(round(x * 4), round(z * 4)) for x, z in pts}
    out = []
    for x, z in pts:
        for r in MOVE:
            for h in (0, 30):
                s = key(x, z, r, h)
                out += [(s, key(x, z, (r - 45) % 360, h)), (s, key(x, z, (r + 45) % 360, h))]
                out.append((s, key(x, z, r, 30 - h)))          # LookDown 0->30 / LookUp 30->0
                dx, dz = MOVE[r]
                if (round(x * 4) + dx, round(z * 4) + dz) in cells:
                    out.append((s, key(x + dx * 0.25, z + dz * 0.25, r, h)))
    return out


def global_map(i: int) -> np.ndarray:
    """(1, G, 7, 7) channels-first map of state i: value = i + g/10 + r/100 + c/1000."""
    g, r, c = np.meshgrid(np.arange(G), np.arange(7), np.arange(7), indexing="ij")
    return (i + g / 10 + r / 100 + c / 1000)[None].astype(np.float32)


def detections(i: int, keyname: str, classes=None) -> np.ndarray:
    """(rows, D + 5): Sink (and GarbageCan) detected where visible; other rows zero."""
    classes = classes or list(K.CATEGORIES)
    out = np.zeros((len(classes), D + 5), np.float32)
    out[:, 0] = -1.0 - np.arange(len(classes))  # row marker, to check the row selection
    if keyname in SINK_AT:
        out[classes.index("Sink"), :D + 5] = [1, 2, 3, 10, 20, 30, 40, 0.875]
    if keyname in CAN_AT:
        out[classes.index("GarbageCan"), D:] = [5, 6, 7, 8, 0.5]
    return out


def write_scene(root, name="FloorPlan401", pts=None, *, classes=None, optimal=True,
                directed=True):
    """Write a complete offline scene folder; returns its path."""
    pts = pts or points()
    folder = root / name
    folder.mkdir(parents=True)
    keys = states(pts)
    links = edges(pts)
    if not directed:  # one link per pair of states
        links = list({tuple(sorted(e)) for e in links})
    (folder / "graph.json").write_text(json.dumps({
        "directed": directed, "multigraph": False, "graph": {},
        "nodes": [{"id": k} for k in keys],
        "links": [{"source": s, "target": t} for s, t in links]}))
    (folder / "grid.json").write_text(json.dumps(
        [{"x": x, "y": 0.9009995, "z": z} for x, z in pts]))
    inside = set(keys)
    vis = {SINK_ID: [k for k in SINK_AT if k in inside], CAN_ID: [k for k in CAN_AT if k in inside],
           "LightSwitch|-00.90|+01.30|+01.25": [],               # present, never visible
           "Towel|+00.20|+00.80|+00.95": [keys[0], keys[1]]}     # not one of the 22
    (folder / "visible_object_map_1.5.json").write_text(json.dumps(vis))
    if optimal:
        table = {k: {} for k in keys}
        if {START, "0.00|1.50|0|0"} <= inside:
            table[START] = {"Sink": 0, "GarbageCan": 4}   # MoveAhead exact; LookDown a tie
            table["0.00|1.50|90|0"] = {"Sink": 5}          # Done where visible: exact
            table["-0.50|1.25|0|0"] = {"Sink": 1}          # RotateLeft: not on a shortest path
            table["0.00|1.50|0|0"] = {"Sink": 5}           # Done where not visible: mismatch
        (folder / "optimal_action.json").write_text(json.dumps(table))
    with h5py.File(folder / "resnet18_featuremap.hdf5", "w") as f:
        for i, k in enumerate(keys):
            f.create_dataset(k, data=global_map(i))
    with h5py.File(folder / "fasterrcnn_features_22cls.hdf5", "w") as f:
        for i, k in enumerate(keys):
            f.create_dataset(k, data=detections(i, k, classes))
    return folder


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    root = tmp_path_factory.mktemp("offline")
    write_scene(root)
    write_scene(root, "FloorPlan402", points(XS[:2], ZS[:1], set()))  # 2 cells: padding
    scenes, report = import_offline(root)
    return scenes, report, root


def idx(scenes, n=0):
    """{state key: the room's local state index} of scene n."""
    return key_index(room(scenes, "pose", n), int(scenes.state_count[n]))


def room(scenes, field, n=0):
    """Scene n's rows of a per-state field (next_state in the room's own indices)."""
    rows = scenes.state_slice(n)
    arr = np.asarray(getattr(scenes, field))[rows]
    return arr - rows.start if field == "next_state" else arr


def test_states_order_and_poses(imported):
    scenes, report, _ = imported
    assert scenes.scene_names == ["FloorPlan401", "FloorPlan402"]
    assert list(np.asarray(scenes.state_count)) == [128, 32]
    assert scenes.num_states == 160 and scenes.max_states == 128   # flat: no padding
    # authors' metres are kept (negative x), so state_key(pose) reproduces their keys
    ix = idx(scenes)
    assert set(ix) == set(states(points()))
    assert tuple(room(scenes, "pose")[ix[START]]) == (-0.5, 1.0, 0, 0)
    # ordered by grid row (z), column (x), heading, horizon: the builder's order
    assert [state_key(p) for p in room(scenes, "pose")[:3]] == [
        "-0.50|1.00|0|0", "-0.50|1.00|0|30", "-0.50|1.00|45|0"]
    assert np.asarray(scenes.room_type).tolist() == [K.ROOM_TYPE_INDEX["bathroom"]] * 2
    assert np.asarray(scenes.split).tolist() == [0, 0]
    assert report["scenes"][0]["ignored_types"] == ["Towel"]
    assert report["scenes"][0]["ignored_edges"] == 0


@pytest.mark.parametrize("start, action, end", [
    ("-0.50|1.00|0|0", K.MOVE_AHEAD, "-0.50|1.25|0|0"),
    ("-0.50|1.00|45|0", K.MOVE_AHEAD, "-0.50|1.00|45|0"),     # into the blocked centre: fails
    ("-0.50|1.25|45|30", K.MOVE_AHEAD, "-0.25|1.50|45|30"),   # diagonal step
    ("0.00|1.00|90|0", K.MOVE_AHEAD, "0.00|1.00|90|0"),       # off the grid: fails
    ("0.00|1.00|180|0", K.MOVE_AHEAD, "0.00|1.00|180|0"),
    ("-0.25|1.00|270|0", K.MOVE_AHEAD, "-0.50|1.00|270|0"),
    ("-0.50|1.00|0|0", K.ROTATE_LEFT, "-0.50|1.00|315|0"),
    ("-0.50|1.00|315|30", K.ROTATE_RIGHT, "-0.50|1.00|0|30"),
    ("-0.50|1.00|0|0", K.LOOK_UP, "-0.50|1.00|0|0"),          # already level
    ("-0.50|1.00|0|0", K.LOOK_DOWN, "-0.50|1.00|0|30"),
    ("-0.50|1.00|0|30", K.LOOK_UP, "-0.50|1.00|0|0"),
    ("-0.50|1.00|0|30", K.LOOK_DOWN, "-0.50|1.00|0|30"),
    ("-0.50|1.00|0|30", K.DONE, "-0.50|1.00|0|30"),
])
def test_transitions(imported, start, action, end):
    scenes, _, _ = imported
    ix = idx(scenes)
    assert int(room(scenes, "next_state")[ix[start], action]) == ix[end]


def test_visibility_presence_and_targets(imported):
    scenes, _, _ = imported
    ix = idx(scenes)
    vis = room(scenes, "visible")
    sink, can, light = (K.category_index(c) for c in ("Sink", "GarbageCan", "LightSwitch"))
    assert sorted(np.flatnonzero(vis[:, sink])) == sorted(ix[k] for k in SINK_AT)
    assert np.flatnonzero(vis[:, can]).tolist() == [ix[CAN_AT[0]]]
    assert vis.sum() == 3
    assert set(np.flatnonzero(scenes.present[0])) == {sink, can, light}
    assert set(np.flatnonzero(scenes.targets[0])) == {sink, can}  # LightSwitch never visible
    # FloorPlan402 (2 cells) lists the same objects; only the GarbageCan is seen there
    assert set(np.flatnonzero(scenes.present[1])) == {sink, can, light}
    assert set(np.flatnonzero(scenes.targets[1])) == {can}


def test_path_lengths_and_expert(imported):
    scenes, _, _ = imported
    ix = idx(scenes)
    sink, can, light = (K.category_index(c) for c in ("Sink", "GarbageCan", "LightSwitch"))
    dist, act = room(scenes, "dist"), room(scenes, "expert_action")
    s = ix[START]
    # Sink: MoveAhead, RotateRight, MoveAhead (diagonal), RotateRight, MoveAhead
    assert dist[s, sink] == 5 and act[s, sink] == K.MOVE_AHEAD
    # from (-0.50, 1.25) facing 0: RotateRight, diagonal, RotateRight, MoveAhead
    assert dist[ix["-0.50|1.25|0|0"], sink] == 4
    assert act[ix["-0.50|1.25|0|0"], sink] == K.ROTATE_RIGHT
    # GarbageCan: three RotateLeft and a LookDown in any order; lowest action index first
    assert dist[s, can] == 4 and act[s, can] == K.ROTATE_LEFT
    assert dist[ix["0.00|1.50|90|30"], sink] == 0 and act[ix["0.00|1.50|90|30"], sink] == K.DONE
    assert (dist[:128, light] == UNREACHABLE).all() and (act[:128, light] == NO_ACTION).all()


def test_optimal_action_comparison_counts_ties_as_agreement(imported):
    _, report, _ = imported
    opt = report["scenes"][0]["optimal_action"]
    assert {k: opt[k] for k in ("compared", "exact", "on_shortest_path", "mismatches",
                                "no_path_here")} == {
        "compared": 5, "exact": 2, "on_shortest_path": 3, "mismatches": 2, "no_path_here": 0}
    bad = {(e["state"], e["authors"]) for e in opt["examples"]}
    assert bad == {("-0.50|1.25|0|0", "RotateLeft"), ("0.00|1.50|0|0", "Done")}


def test_features_transposed_and_rows_selected(imported):
    scenes, _, _ = imported
    ix = idx(scenes)
    order = {k: i for i, k in enumerate(states(points()))}  # file order of the datasets
    sink = K.category_index("Sink")
    assert scenes.global_feat.dtype == np.float16 and scenes.appearance.dtype == np.float16
    assert scenes.global_basis is None and scenes.appearance_basis is None
    assert scenes.global_dim == G and scenes.appearance_dim == D
    for k in (START, SINK_AT[0]):
        want = global_map(order[k])[0].transpose(1, 2, 0).astype(np.float16)
        np.testing.assert_array_equal(room(scenes, "global_feat")[ix[k]], want)
    s = ix[SINK_AT[1]]
    np.testing.assert_array_equal(room(scenes, "appearance")[s, sink], [1, 2, 3])
    np.testing.assert_array_equal(room(scenes, "det_box")[s, sink], [10, 20, 30, 40])
    assert room(scenes, "det_conf")[s, sink] == np.float16(0.875)
    np.testing.assert_array_equal(room(scenes, "appearance")[ix[START], :, 0],
                                  (-1.0 - np.arange(22)).astype(np.float16))


def test_ragged_rooms_are_stored_flat(imported):
    """128- and 32-state rooms take 160 rows (nothing padded); the small room's moves are
    global indices inside its own run; padded back (flat.to_padded), it follows the old
    padding conventions."""
    from orgnav_jax.scenes.sceneset.flat import to_padded
    scenes, _, _ = imported
    assert np.asarray(scenes.state_offset).tolist() == [0, 128]
    nxt = np.asarray(scenes.next_state)
    assert nxt.shape == (160, K.NUM_ACTIONS)
    assert (nxt[128:] >= 128).all() and (nxt[128:] < 160).all() and (nxt[:128] < 128).all()
    pad = np.arange(32, 128)
    assert (to_padded(scenes, "next_state")[1, pad] == pad[:, None]).all()
    assert (to_padded(scenes, "dist", UNREACHABLE)[1, pad] == UNREACHABLE).all()
    assert (to_padded(scenes, "expert_action", NO_ACTION)[1, pad] == NO_ACTION).all()
    assert not to_padded(scenes, "visible")[1, pad].any()
    np.testing.assert_array_equal(to_padded(scenes, "dist")[1, :32], room(scenes, "dist", 1))
    scenes.validate()


def test_sixty_row_detections_need_and_use_an_explicit_row_list(tmp_path, imported):
    scenes, _, _ = imported
    classes = [f"Other{i}" for i in range(38)] + list(K.CATEGORIES)
    classes = classes[::2] + classes[1::2]  # interleave: the 22 are scattered over 60 rows
    write_scene(tmp_path, classes=classes)
    with pytest.raises(OfflineFormatError, match=r"60 rows.*detection_rows"):
        import_offline(tmp_path)
    by_name, _ = import_offline(tmp_path, detection_rows=classes)
    by_index, _ = import_offline(tmp_path, detection_rows=[classes.index(c)
                                                           for c in K.CATEGORIES])
    for got in (by_name, by_index):
        np.testing.assert_array_equal(got.det_box, room(scenes, "det_box"))
        np.testing.assert_array_equal(got.appearance[..., 1:],
                                      room(scenes, "appearance")[..., 1:])


def test_undirected_graph_and_single_scene_folder(tmp_path, imported):
    scenes, _, _ = imported
    folder = write_scene(tmp_path, directed=False)
    got, report = import_offline(folder)  # the scene folder itself
    assert got.scene_names == ["FloorPlan401"]
    np.testing.assert_array_equal(got.next_state, room(scenes, "next_state"))
    assert report["scenes"][0]["ignored_edges"] == 0


def test_strict_types_names_the_type(tmp_path):
    write_scene(tmp_path)
    with pytest.raises(OfflineFormatError, match=r"visible_object_map_1\.5\.json.*'Towel'"):
        import_offline(tmp_path, unknown_types="error")


def test_episodes_json_and_pickle_with_unreachable_target(tmp_path, imported):
    scenes, _, _ = imported
    records = [
        {"scene": "FloorPlan401", "goal_object_type": "Sink", "task_data": [SINK_ID],
         "state": START},
        {"scene": "FloorPlan401", "goal_object_type": "GarbageCan", "task_data": [CAN_ID],
         "state": START},
        {"scene": "FloorPlan401", "goal_object_type": "LightSwitch",
         "task_data": ["LightSwitch|-00.90|+01.30|+01.25"], "state": START},  # unreachable
    ]
    (tmp_path / "eps.json").write_text(json.dumps(records))
    (tmp_path / "eps.pkl").write_bytes(pickle.dumps(records, protocol=2))
    for name in ("eps.json", "eps.pkl"):
        with pytest.warns(UserWarning, match="skipped 1 episode"):
            eps, skipped = load_offline_episodes(tmp_path / name, scenes)
        assert skipped == 1 and len(eps) == 2
        assert eps.optimal_len.tolist() == [5, 4]
        assert eps.start.tolist() == [idx(scenes)[START]] * 2
