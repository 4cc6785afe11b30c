"""sceneset/assemble.py, the contract of a scene source: rooms given as per-room arrays
(local state indices) become the SceneSet, whatever the source; wrong shapes name the
room and the field."""

from __future__ import annotations

import numpy as np
import pytest

from orgnav_jax.scenes.sceneset.assemble import FEATURE_FIELDS, SourceRoom, assemble

BASES = ("appearance_proto", "appearance_basis", "global_basis")


def source_rooms(s, callable_features: bool = False) -> list[SourceRoom]:
    """The rooms of SceneSet s as a source would deliver them (local indices)."""
    rooms = []
    for n in range(len(s.state_count)):
        o, k = int(s.state_offset[n]), int(s.state_count[n])
        rows = slice(o, o + k)
        feats = {f: np.asarray(getattr(s, f)[rows]) for f in FEATURE_FIELDS}
        if callable_features:
            feats = writer(feats)
        rooms.append(SourceRoom(
            scene_id=int(s.scene_id[n]), room_type=int(s.room_type[n]), split=int(s.split[n]),
            next_state=np.asarray(s.next_state[rows]) - o, pose=np.asarray(s.pose[rows]),
            visible=np.asarray(s.visible[rows]), present=np.asarray(s.present[n]),
            features=feats))
    return rooms


def writer(feats: dict):
    """The features as a source that writes them into the views assemble hands it."""
    def write(views: dict) -> None:
        for f in FEATURE_FIELDS:
            views[f][...] = feats[f]
    return write


def assert_same_set(a, b):
    for name in ("next_state", "pose", "visible", "present", "targets", "state_offset",
                 "state_count", "dist", "expert_action", "room_type", "scene_id", "split",
                 *FEATURE_FIELDS, *BASES):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)
            assert np.asarray(x).dtype == np.asarray(y).dtype, name
    assert a.info == b.info


@pytest.mark.parametrize("callable_features", [False, True])
def test_a_sets_rooms_assemble_to_the_same_set(tiny_scenes, callable_features):
    """The generator's rooms handed back as a source's rooms (dict or writer features)
    give the same SceneSet: layout, expert tables, targets and stored features."""
    s = tiny_scenes
    widths = (s.appearance.shape[-1], s.global_feat.shape[-1])
    again = assemble(source_rooms(s, callable_features), s.info, widths=widths,
                     **{b: getattr(s, b) for b in BASES})
    assert_same_set(again, s)
    again.validate()


def test_rooms_in_any_order_are_grouped_by_split(tiny_scenes):
    """Rooms given in reverse keep their order on the scene axis, while their states are
    laid out split by split (train, val, test: a split view is one slice)."""
    s = tiny_scenes
    rooms = source_rooms(s)[::-1]
    again = assemble(rooms, s.info, **{b: getattr(s, b) for b in BASES})
    assert list(np.asarray(again.scene_id)) == [r.scene_id for r in rooms]
    by_offset = np.argsort(np.asarray(again.state_offset))
    split_of_states = np.asarray(again.split)[by_offset]
    assert (np.diff(split_of_states) >= 0).all() and len(set(split_of_states)) == 3


@pytest.mark.parametrize("field, value, expected", [
    ("next_state", lambda r: r.next_state[:, :5], "next_state has shape"),
    ("present", lambda r: r.present[:-1], "present has shape"),
    ("features", lambda r: dict(r.features, det_conf=r.features["det_conf"][:-1]),
     "feature 'det_conf' has shape"),
])
def test_a_wrong_shape_names_the_room_and_the_field(tiny_scenes, field, value, expected):
    rooms = source_rooms(tiny_scenes)
    r = rooms[3]
    setattr(r, field, value(r))
    with pytest.raises(ValueError, match=rf"room 3 \(scene_id {r.scene_id}\): {expected}"):
        assemble(rooms, tiny_scenes.info)
