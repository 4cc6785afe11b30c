"""Bad offline data: every case raises OfflineFormatError (a ValueError, never a bare
KeyError) whose message names the file, field or state key at fault."""

from __future__ import annotations

import json
import pickle
import re
from collections import OrderedDict

import h5py
import numpy as np
import pytest

from test_offline_handmade import CAN_AT, SINK_AT, START, write_scene

from orgnav_jax.constants import CATEGORIES
from orgnav_jax.scenes.offline.episodes import load_offline_episodes, read_records
from orgnav_jax.scenes.offline import OfflineFormatError, import_offline


@pytest.fixture
def scene(tmp_path):
    return write_scene(tmp_path / "data")


def edit_json(path, fn):
    path.write_text(json.dumps(fn(json.loads(path.read_text()))))


def rename_node(doc, old, new):
    for node in doc["nodes"]:
        if node["id"] == old:
            node["id"] = new
    for link in doc["links"]:
        for end in ("source", "target"):
            if link[end] == old:
                link[end] = new
    return doc


def expect(root, pattern, **kwargs):
    with pytest.raises(OfflineFormatError, match=pattern) as info:
        import_offline(root, **kwargs)
    return str(info.value)


# ------------------------------------------------------------------ files and folders
@pytest.mark.parametrize("name, pattern", [
    ("graph.json", r"graph\.json: missing file"),
    ("grid.json", r"grid\.json: missing file"),
    ("visible_object_map_1.5.json", r"missing file visible_object_map_1\.5\.json"),
    ("resnet18_featuremap.hdf5", r"resnet18_featuremap\.hdf5: missing file"),
    ("fasterrcnn_features_22cls.hdf5", r"missing detection hdf5 \(tried fasterrcnn_features_22cls"),
])
def test_missing_file(scene, name, pattern):
    (scene / name).unlink()
    expect(scene.parent, pattern)


def test_no_scene_folders_and_unknown_scene(tmp_path, scene):
    (tmp_path / "empty").mkdir()
    expect(tmp_path / "empty", r"no FloorPlanN scene folders")
    expect(scene.parent, r"no scene folder\(s\) 'FloorPlan9'", scenes=["FloorPlan9"])


def test_scene_folder_name_and_number(tmp_path):
    write_scene(tmp_path / "a", "Kitchen1")
    expect(tmp_path / "a" / "Kitchen1", r"scene folder 'Kitchen1' is not named FloorPlanN")
    write_scene(tmp_path / "b", "FloorPlan77")
    expect(tmp_path / "b", r"FloorPlan77 is not an AI2-THOR room number")


def test_invalid_json(scene):
    (scene / "graph.json").write_text('{"nodes": [')
    expect(scene.parent, r"graph\.json: not valid JSON")


def test_graph_structure(scene):
    edit_json(scene / "graph.json", lambda d: {"nodes": d["nodes"]})
    expect(scene.parent, r"graph\.json: expected a 'links' \(or 'edges'\) list")


# ------------------------------------------------------------------ state keys
def test_malformed_state_key(scene):
    edit_json(scene / "graph.json", lambda d: rename_node(d, START, "-0.50|abc|0|0"))
    expect(scene.parent, r"graph\.json: malformed state key '-0\.50\|abc\|0\|0'")


@pytest.mark.parametrize("bad, pattern", [
    ("-0.50|1.00|30|0", r"rotation 30, expected one of 0, 45"),
    ("-0.50|1.00|0|60", r"horizon 60, expected one of \[0, 30\]"),
    ("-0.5|1.00|0|0", r"'-0\.5\|1\.00\|0\|0' is not in canonical form '-0\.50\|1\.00\|0\|0'"),
])
def test_state_key_values(scene, bad, pattern):
    edit_json(scene / "graph.json", lambda d: rename_node(d, START, bad))
    expect(scene.parent, pattern)


def test_key_in_graph_but_not_in_hdf5(scene):
    with h5py.File(scene / "resnet18_featuremap.hdf5", "a") as f:
        del f[START]
    msg = expect(scene.parent, r"1 state key\(s\) in .*graph\.json but not in "
                               r".*resnet18_featuremap\.hdf5")
    assert START in msg


def test_key_in_hdf5_but_not_in_graph(scene):
    with h5py.File(scene / "fasterrcnn_features_22cls.hdf5", "a") as f:
        f.create_dataset("9.00|9.00|0|0", data=np.zeros((22, 8), np.float32))
    expect(scene.parent, r"in .*fasterrcnn_features_22cls\.hdf5 but not in .*graph\.json: "
                         r"'9\.00\|9\.00\|0\|0'")


def test_visibility_lists_unknown_state(scene):
    edit_json(scene / "visible_object_map_1.5.json",
              lambda d: {**d, "Bowl|+00.00|+00.90|+00.00": ["5.00|5.00|0|0"]})
    expect(scene.parent, r"visible_object_map_1\.5\.json: objectId 'Bowl\|\+00\.00\|\+00\.90\|"
                         r"\+00\.00' lists 1 state key\(s\) not in graph\.json: '5\.00")


def test_optimal_action_key_not_in_graph(scene):
    edit_json(scene / "optimal_action.json", lambda d: {**d, "7.00|7.00|0|0": {"Sink": 0}})
    expect(scene.parent, r"optimal_action\.json but not in .*graph\.json: '7\.00\|7\.00\|0\|0'")


def test_optimal_action_bad_value(scene):
    edit_json(scene / "optimal_action.json", lambda d: {**d, START: {"Sink": 9}})
    expect(scene.parent, r"optimal_action\.json: state '-0\.50\|1\.00\|0\|0' target 'Sink' "
                         r"has action 9, expected an index 0\.\.5")


def test_state_position_not_in_grid(scene):
    edit_json(scene / "grid.json", lambda pts: [p for p in pts if p["x"] != 0.0])
    expect(scene.parent, r"grid\.json: 3 position\(s\) of graph\.json states are not "
                         r"reachable points")


# ------------------------------------------------------------------ graph edges
def test_edge_matching_no_action(scene):
    jump = ("-0.50|1.00|0|0", "-0.50|1.50|0|0")  # two cells at once
    edit_json(scene / "graph.json",
              lambda d: {**d, "links": d["links"] + [{"source": jump[0], "target": jump[1]}]})
    expect(scene.parent, r"1 edge\(s\) match no action .*'-0\.50\|1\.00\|0\|0 -> "
                         r"-0\.50\|1\.50\|0\|0'")
    _, report = import_offline(scene.parent, unmatched_edges="ignore")
    assert report["scenes"][0]["ignored_edges"] == 1


def test_link_to_unknown_node(scene):
    edit_json(scene / "graph.json", lambda d: {**d, "links": d["links"] + [
        {"source": START, "target": "3.00|3.00|0|0"}]})
    expect(scene.parent, r"graph\.json: 1 link end\(s\) are not graph nodes: '3\.00")


# ------------------------------------------------------------------ objects
def test_type_outside_the_22_in_strict_mode(scene):
    expect(scene.parent, r"object type 'Towel' is not one of the 22 categories",
           unknown_types="error")


def test_malformed_object_id(scene):
    edit_json(scene / "visible_object_map_1.5.json", lambda d: {**d, "Sink": SINK_AT})
    expect(scene.parent, r"visible_object_map_1\.5\.json: malformed objectId 'Sink'")


def test_raw_metadata_instead_of_visibility_map(scene):
    (scene / "visible_object_map_1.5.json").write_text(json.dumps({START: {"objects": []}}))
    expect(scene.parent, r"keyed by state .* raw per-state metadata")


# ------------------------------------------------------------------ hdf5 shapes and rows
def test_channels_last_resnet_map(scene):
    with h5py.File(scene / "resnet18_featuremap.hdf5", "a") as f:
        for k in list(f):
            del f[k]
            f.create_dataset(k, data=np.zeros((1, 7, 7, 4), np.float32))
    expect(scene.parent, r"resnet18_featuremap\.hdf5: dataset .* has shape \(1, 7, 7, 4\), "
                         r"expected \(1, G, 7, 7\)")


def test_one_dataset_of_another_shape(scene):
    with h5py.File(scene / "fasterrcnn_features_22cls.hdf5", "a") as f:
        del f[CAN_AT[0]]
        f.create_dataset(CAN_AT[0], data=np.zeros((22, 9), np.float32))
    expect(scene.parent, r"fasterrcnn_features_22cls\.hdf5: dataset '-0\.50\|1\.00\|225\|30' "
                         r"has shape \(22, 9\), expected \(22, 8\)")


def test_feature_widths_differ_between_scenes(tmp_path):
    write_scene(tmp_path)
    other = write_scene(tmp_path, "FloorPlan402")
    with h5py.File(other / "fasterrcnn_features_22cls.hdf5", "a") as f:
        for k in list(f):
            del f[k]
            f.create_dataset(k, data=np.zeros((22, 10), np.float32))
    expect(tmp_path, r"FloorPlan402: feature shapes .* differ from FloorPlan401's")


def test_detection_rows_without_mapping_and_bad_mapping(tmp_path):
    classes = [f"Other{i}" for i in range(38)] + list(CATEGORIES)
    write_scene(tmp_path, classes=classes)
    expect(tmp_path, r"detection datasets have 60 rows, not 22.*--detection-classes")
    expect(tmp_path, r"21 class names given for detection datasets of 60 rows",
           detection_rows=classes[:21])
    expect(tmp_path, r"detection rows must be 22 indices in \[0, 60\)",
           detection_rows=list(range(40, 62)))
    expect(tmp_path, r"lacks categories 'AlarmClock'",
           detection_rows=classes[:38] + ["X"] + classes[39:])


def test_not_an_hdf5_file(scene):
    (scene / "resnet18_featuremap.hdf5").write_text("not hdf5")
    expect(scene.parent, r"resnet18_featuremap\.hdf5: cannot open as HDF5")


# ------------------------------------------------------------------ episodes
class Thing:
    pass


def test_pickle_needing_a_class_is_refused(tmp_path, scene):
    path = tmp_path / "eps.pkl"
    path.write_bytes(pickle.dumps([OrderedDict(scene="FloorPlan401")]))
    with pytest.raises(OfflineFormatError, match=r"eps\.pkl: cannot read the pickle: the "
                                                 r"pickle needs collections\.OrderedDict"):
        read_records(path)
    path.write_bytes(pickle.dumps(Thing()))
    with pytest.raises(OfflineFormatError, match=r"needs test_offline_errors\.Thing; only "
                                                 r"plain dicts"):
        read_records(path)


@pytest.fixture(scope="module")
def small_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("eps")
    write_scene(root)
    return import_offline(root)[0]


@pytest.mark.parametrize("record, pattern", [
    ({"scene": "FloorPlan401", "goal_object_type": "Sink", "task_data": ["Bowl|+0|+0|+0"],
      "state": START}, (r"episode 0 task_data objectId 'Bowl\|\+0\|\+0\|\+0' is a Bowl, "
                        r"but goal_object_type is 'Sink'")),
    ({"scene": "FloorPlan401", "goal_object_type": "Towel", "state": START},
     r"episode 0: unknown category 'Towel'"),
    ({"scene": "FloorPlan401", "goal_object_type": "Sink", "state": "9.00|9.00|0|0"},
     r"state '9\.00\|9\.00\|0\|0' is not a state of FloorPlan401"),
    ({"scene": "FloorPlan401", "state": START}, r"lacks field\(s\) \['goal_object_type'\]"),
])
def test_bad_episode_records(tmp_path, small_set, record, pattern):
    path = tmp_path / "eps.json"
    path.write_text(json.dumps([record]))
    with pytest.raises(OfflineFormatError, match=pattern):
        load_offline_episodes(path, small_set)


def test_unreachable_target_is_warned_skipped_and_counted(tmp_path, small_set):
    path = tmp_path / "eps.json"
    path.write_text(json.dumps([{"scene": "FloorPlan401", "goal_object_type": g,
                                 "task_data": [], "state": START}
                                for g in ("LightSwitch", "Sink", "LightSwitch")]))
    with pytest.warns(UserWarning, match=re.escape("skipped 2 episode(s) whose target is "
                                                   "unreachable")):
        eps, skipped = load_offline_episodes(path, small_set)
    assert skipped == 2 and len(eps) == 1
    with pytest.raises(OfflineFormatError, match="LightSwitch is not a valid target"):
        load_offline_episodes(path, small_set, on_unreachable="error")


# ------------------------------------------------------------------ typed JSON (issue 22)
def _set_first_point(text):
    def edit(points):
        points[0] = "@P@"
        return points
    return lambda path: path.write_text(
        json.dumps(edit(json.loads(path.read_text()))).replace('"@P@"', text))


@pytest.mark.parametrize("point", ['{"x": 1e400, "y": 0.9, "z": 0.0}',
                                   '{"x": true, "y": 0.9, "z": 0.0}',
                                   '{"x": null, "y": 0.9, "z": 0.0}',
                                   '{"x": "0.00", "y": 0.9, "z": 0.0}',
                                   '{"y": 0.9, "z": 0.0}', "[0.0, 0.9, 0.0]"])
def test_grid_point_of_wrong_type(scene, point):
    _set_first_point(point)(scene / "grid.json")
    msg = expect(scene.parent, r"grid\.json: point 0 is .*, expected \{'x': float, 'y': "
                               r"float, 'z': float\} \(finite numbers\)")
    assert "\n" not in msg


@pytest.mark.parametrize("value", ["false", '"no"', "null", "0"])
def test_graph_directed_of_wrong_type(scene, value):
    if value == "false":                        # a proper boolean is read
        edit_json(scene / "graph.json", lambda d: {**d, "directed": False})
        import_offline(scene.parent)
        return
    text = json.dumps({**json.loads((scene / "graph.json").read_text()), "directed": "@"})
    (scene / "graph.json").write_text(text.replace('"@"', value))
    expect(scene.parent, rf"graph\.json: field 'directed' is {re.escape(repr(json.loads(value)))}"
                         r", expected true or false")


@pytest.mark.parametrize("doc, pattern", [
    ('{"FloorPlan401": null}', r"room 'FloorPlan401' has split None, expected one of"),
    ('{"FloorPlan401": ["val"]}', r"room 'FloorPlan401' has split \['val'\], expected one of"),
    ('{"FloorPlan401": {"split": 3}}', r"room 'FloorPlan401' has split 3, expected one of"),
    ('{"FloorPlan401": {"split": "val", "room_type": ["kitchen"]}}',
     r"room 'FloorPlan401' has room_type \['kitchen'\], expected one of"),
    ('{"FloorPlan401": {"room_type": "kitchen"}}', r"room 'FloorPlan401' maps to .*, expected \{'split'"),
    ('["FloorPlan401"]', r"holds a JSON list, expected an object"),
])
def test_splits_file_of_wrong_types(tmp_path, doc, pattern):
    from orgnav_jax.scenes.offline.splits import read_splits
    path = tmp_path / "splits.json"
    path.write_text(doc)
    with pytest.raises(OfflineFormatError, match=rf"--splits {re.escape(str(path))}: "
                                                 + pattern):
        read_splits(path)


@pytest.mark.parametrize("field, value, pattern", [
    ("scene", ["FloorPlan401"], r"episode 0: field 'scene': expected a string, got \["),
    ("state", {"x": 1}, r"episode 0: field 'state': expected a string, got \{"),
    ("goal_object_type", 3, r"episode 0: field 'goal_object_type': expected a string, got 3"),
    ("optimal_len", float("inf"), r"episode 0: field 'optimal_len': expected an integer "
                                  r"0 <= optimal_len <= 2,147,483,647, got inf"),
    ("optimal_len", "4", r"episode 0: field 'optimal_len': expected an integer .*, got '4'"),
])
def test_episode_record_fields_of_wrong_type(tmp_path, small_set, field, value, pattern):
    path = tmp_path / "eps.json"
    record = {"scene": "FloorPlan401", "goal_object_type": "Sink", "state": START,
              field: value}
    path.write_text(json.dumps([record]))          # inf is written as Infinity
    with pytest.raises(OfflineFormatError, match=re.escape(str(path)) + ": " + pattern):
        load_offline_episodes(path, small_set)


@pytest.mark.parametrize("file, shape, pattern", [
    ("resnet18_featuremap.hdf5", (1, 0, 7, 7), r"resnet18_featuremap\.hdf5: dataset .* has "
     r"shape \(1, 0, 7, 7\): 0 feature channels, expected G >= 1"),
    ("fasterrcnn_features_22cls.hdf5", (22, 5), r"fasterrcnn_features_22cls\.hdf5: dataset .* "
     r"has shape \(22, 5\), expected \(22, 517\)"),
])
def test_features_of_zero_channels_are_refused_at_import(scene, file, shape, pattern):
    with h5py.File(scene / file, "a") as f:
        for k in list(f):
            del f[k]
            f.create_dataset(k, data=np.zeros(shape, np.float32))
    expect(scene.parent, pattern)
