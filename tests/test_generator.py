"""The procedural generator: determinism, room structure, sizes, splits, contents and
the co-occurrence statistic the benchmark is built around."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import scenes
from orgnav_jax.scenes.synthetic import builder, catalog, layout
from orgnav_jax.scenes.synthetic.presets import get_preset

ROOM_ARRAYS = ("wall", "furniture", "block_height", "reachable", "obj_category",
               "obj_center", "obj_size", "obj_height")


def _same_room(a: layout.Room, b: layout.Room) -> bool:
    if (a.floorplan, a.room_type, a.door) != (b.floorplan, b.room_type, b.door):
        return False
    for f in ROOM_ARRAYS:
        x, y = getattr(a, f), getattr(b, f)
        if x.shape != y.shape or x.dtype != y.dtype or not np.array_equal(x, y):
            return False
    return True


def _rooms_of(room_type: str, n: int, seed: int = 0) -> list[layout.Room]:
    base = K.FLOORPLAN_OFFSET[room_type]
    return [layout.generate_room(seed, base + k) for k in range(1, n + 1)]


# ------------------------------------------------------------------ determinism
@pytest.mark.parametrize("fp", [1, 27, 205, 230, 310, 404])
def test_generate_room_deterministic(fp):
    a = layout.generate_room(0, fp)
    layout.generate_room(0, fp + 1 if fp % 100 < 30 else fp - 1)  # other rooms in between
    b = layout.generate_room(0, fp)
    assert _same_room(a, b)
    assert a.floorplan == fp and a.name == f"FloorPlan{fp}"
    assert a.room_type == layout.room_type_of(fp)


@pytest.mark.parametrize("fp", [1, 2, 205, 310, 404])
def test_other_seed_gives_other_room(fp):
    a, b = layout.generate_room(0, fp), layout.generate_room(1, fp)
    assert not _same_room(a, b)
    # and neighbouring floorplans differ too
    assert not _same_room(a, layout.generate_room(0, fp + 1))


def test_room_arrays_deterministic():
    a = builder.room_arrays(0, 401, "val")
    b = builder.room_arrays(0, 401, "val", room=layout.generate_room(0, 401))
    for f in dataclasses.fields(builder.RoomArrays):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, f.name
    assert a.split == K.SPLIT_INDEX["val"] and a.room_type == K.ROOM_TYPE_INDEX["bathroom"]
    S = a.pose.shape[0]
    assert S == 16 * int(layout.generate_room(0, 401).reachable.sum())
    assert a.next_state.shape == (S, K.NUM_ACTIONS)
    assert a.visible.shape == a.det_conf.shape == (S, K.NUM_CATEGORIES)
    assert a.global_feat.shape[:3] == (S, 7, 7)


def test_build_deterministic(tiny_scenes):
    """A second build (only the first train room of each type) equals the matching
    rows of the pytest session's tiny build, field by field, on each room's states (next_state
    in the room's own indices: the two sets lay their rooms out differently)."""
    small = scenes.build("tiny", 0, rooms_per_type=(1, 0, 0))
    full = tiny_scenes
    assert small.num_scenes == 4
    assert sorted(np.asarray(small.scene_id).tolist()) == [1, 201, 301, 401]
    per_state = {"next_state", "pose", "visible", "dist", "expert_action",
                 "det_box", "det_conf", "appearance", "global_feat"}
    shared = {"appearance_proto", "appearance_basis", "global_basis", "global_scale",
              "appearance_scale"}
    full_ids = np.asarray(full.scene_id).tolist()
    for n, sid in enumerate(np.asarray(small.scene_id).tolist()):
        m = full_ids.index(sid)
        rs, rf = small.state_slice(n), full.state_slice(m)
        assert rs.stop - rs.start == rf.stop - rf.start
        for f in dataclasses.fields(small):
            if f.name in shared or f.name in ("info", "state_offset"):
                continue
            if f.name in per_state:
                x = np.asarray(getattr(small, f.name))[rs]
                y = np.asarray(getattr(full, f.name))[rf]
                if f.name == "next_state":
                    x, y = x - rs.start, y - rf.start
            else:
                x = np.asarray(getattr(small, f.name))[n]
                y = np.asarray(getattr(full, f.name))[m]
            assert x.dtype == y.dtype, f.name
            if not np.array_equal(x, y):
                np.testing.assert_array_equal(x, y, err_msg=f"{f.name} FloorPlan{sid}")
    for name in shared:
        np.testing.assert_array_equal(getattr(small, name), getattr(full, name), err_msg=name)
    assert small.meta("preset") == full.meta("preset") == "tiny"
    assert small.meta("seed") == full.meta("seed") == 0


# --------------------------------------------------------------- room structure
def test_room_structure(sample_rooms):
    for fp, r in sample_rooms.items():
        H, W = r.wall.shape
        name = r.name
        assert r.wall[0].all() and r.wall[-1].all() and r.wall[:, 0].all() and r.wall[:, -1].all()
        assert np.isinf(r.block_height[r.wall]).all(), name
        assert np.isfinite(r.block_height[~r.wall]).all(), name
        free = ~r.wall & (r.furniture < 0) & (r.block_height == 0)
        assert not (r.reachable & ~free).any(), name
        assert (r.block_height[r.furniture >= 0] > 0).all(), name
        # one 8-connected component
        cells = {tuple(c) for c in np.argwhere(r.reachable)}
        start = next(iter(cells))
        todo, seen = [start], {start}
        while todo:
            i, j = todo.pop()
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    nb = (i + di, j + dj)
                    if nb in cells and nb not in seen:
                        seen.add(nb)
                        todo.append(nb)
        assert seen == cells, name
        # the door is a wall cell next to a reachable-or-free interior cell
        di, dj = r.door
        assert r.wall[di, dj]
        nbs = [(di + a, dj + b) for a, b in ((-1, 0), (1, 0), (0, -1), (0, 1))
               if 0 <= di + a < H and 0 <= dj + b < W]
        assert any(not r.wall[p] for p in nbs), name
        # objects lie inside the room
        x, y, z = r.obj_center.T
        assert ((x >= 0) & (x <= (W - 1) * K.GRID_SIZE)).all(), name
        assert ((z >= 0) & (z <= (H - 1) * K.GRID_SIZE)).all(), name
        assert (y > 0).all() and (y < 2.6).all(), name
        k = len(r.obj_category)
        assert r.obj_center.shape == (k, 3) and r.obj_size.shape == r.obj_height.shape == (k,)
        np.testing.assert_allclose(
            r.obj_size, [catalog.OBJECTS[K.CATEGORIES[c]].size for c in r.obj_category])


SURFACE_OBJECTS = ("AlarmClock", "Book", "Bowl", "CellPhone", "CoffeeMachine", "DeskLamp",
                   "Kettle", "Laptop", "Microwave", "Pan", "Plate", "Pot", "RemoteControl",
                   "Toaster", "StoveBurner", "Television")
FLOOR_OBJECTS = ("Chair", "FloorLamp", "Fridge", "GarbageCan")


def test_objects_rest_on_furniture_or_floor(sample_rooms):
    for fp, r in sample_rooms.items():
        for k, c in enumerate(r.obj_category):
            name = K.CATEGORIES[c]
            x, y, z = (float(v) for v in r.obj_center[k])
            bottom = y - float(r.obj_height[k]) / 2
            i, j = int(round(z / K.GRID_SIZE)), int(round(x / K.GRID_SIZE))
            where = f"{r.name} {name} at cell {(i, j)}"
            if name in SURFACE_OBJECTS:
                kind = catalog.FURNITURE[r.furniture[i, j]]
                assert r.furniture[i, j] >= 0 and kind.is_surface, where
                assert bottom == pytest.approx(kind.height, abs=1e-4), where
            elif name in FLOOR_OBJECTS:
                assert bottom == pytest.approx(0.0, abs=1e-4), where
                ci, cj = z / K.GRID_SIZE, x / K.GRID_SIZE
                for a in {math.floor(ci + 1e-6), math.ceil(ci - 1e-6)}:
                    for b in {math.floor(cj + 1e-6), math.ceil(cj - 1e-6)}:
                        assert not r.reachable[a, b], where
                        if catalog.OBJECTS[name].blocks:
                            assert r.block_height[a, b] == pytest.approx(
                                catalog.OBJECTS[name].height), where
            elif name == "LightSwitch":
                lo, hi = layout.WALL_OBJECT_HEIGHT
                assert lo - 1e-4 <= y <= hi + 1e-4, where
                # within 0.2 m (horizontally) of a wall cell centre
                walls = np.argwhere(r.wall) * K.GRID_SIZE
                d = np.hypot(walls[:, 0] - z, walls[:, 1] - x).min()
                assert d <= 0.2, where
            elif name == "Sink":
                assert catalog.FURNITURE[r.furniture[i, j]].name in ("sink_counter",
                                                                     "vanity"), where


def test_invalid_floorplans_rejected():
    assert layout.room_type_of(30) == "kitchen"
    assert layout.room_type_of(201) == "living_room"
    assert layout.room_type_of(330) == "bedroom"
    assert layout.room_type_of(430) == "bathroom"
    for fp in (0, 31, 200, 231, 431, -1):
        with pytest.raises(ValueError, match=str(fp)):
            layout.room_type_of(fp)
    with pytest.raises(ValueError, match="31"):
        layout.generate_room(0, 31)


# ------------------------------------------------------------------- room sizes
def test_reachable_counts_within_range(sample_rooms, tiny_scenes):
    for fp, r in sample_rooms.items():
        lo, hi = layout.REACHABLE_RANGE[r.room_type]
        assert lo <= int(r.reachable.sum()) <= hi, r.name
    counts = np.asarray(tiny_scenes.state_count)
    for n in range(tiny_scenes.num_scenes):
        rt = K.ROOM_TYPES[int(tiny_scenes.room_type[n])]
        lo, hi = layout.REACHABLE_RANGE[rt]
        assert counts[n] % 16 == 0
        assert lo <= counts[n] // 16 <= hi, tiny_scenes.scene_names[n]


def test_room_sizes_ordered_by_type():
    mean = {rt: np.mean([r.reachable.sum() for r in _rooms_of(rt, 6)]) for rt in K.ROOM_TYPES}
    assert mean["bathroom"] < min(mean["kitchen"], mean["bedroom"], mean["living_room"])
    assert mean["living_room"] > max(mean["kitchen"], mean["bedroom"], mean["bathroom"])
    assert mean["bathroom"] < 0.5 * mean["living_room"]


# ----------------------------------------------------------------------- splits
def test_split_numbering_in_tiny_set(tiny_scenes):
    ids = np.asarray(tiny_scenes.scene_id)
    split = np.asarray(tiny_scenes.split)
    rtype = np.asarray(tiny_scenes.room_type)
    assert len(set(ids.tolist())) == len(ids)
    sets = {k: set(ids[split == K.SPLIT_INDEX[k]].tolist()) for k in K.SPLITS}
    assert not (sets["train"] & sets["val"]) and not (sets["train"] & sets["test"])
    assert not (sets["val"] & sets["test"])
    for sid, sp, rt in zip(ids, split, rtype):
        off = K.FLOORPLAN_OFFSET[K.ROOM_TYPES[rt]]
        k = int(sid) - off
        assert layout.room_type_of(int(sid)) == K.ROOM_TYPES[rt]
        if K.SPLITS[sp] == "train":
            assert 1 <= k <= 20
        elif K.SPLITS[sp] == "val":
            assert 21 <= k <= 29 and k % 2 == 1
        else:
            assert 22 <= k <= 30 and k % 2 == 0
    # tiny: 2/1/1 rooms of each type
    for rt in range(len(K.ROOM_TYPES)):
        counts = [int(((rtype == rt) & (split == s)).sum()) for s in range(3)]
        assert counts == [2, 1, 1]
    assert tiny_scenes.scene_names[0] == f"FloorPlan{ids[0]}"


def test_full_preset_floorplans_follow_ai2thor():
    plans = get_preset("small").floorplans()
    assert len(plans) == 120
    for rt in K.ROOM_TYPES:
        off = K.FLOORPLAN_OFFSET[rt]
        by = {s: sorted(fp for fp, t, s2 in plans if t == rt and s2 == s) for s in K.SPLITS}
        assert by["train"] == [off + k for k in range(1, 21)]
        assert by["val"] == [off + k for k in range(21, 30, 2)]
        assert by["test"] == [off + k for k in range(22, 31, 2)]
    assert len({fp for fp, _, _ in plans}) == 120


# ---------------------------------------------------------------------- contents
def test_targets_of_room_type_are_present():
    rooms = {rt: _rooms_of(rt, 15) for rt in K.ROOM_TYPES}
    pairs = hits = 0
    for rt, rs in rooms.items():
        for name in K.TARGETS[rt]:
            c = K.category_index(name)
            frac = np.mean([c in set(r.obj_category.tolist()) for r in rs])
            assert frac >= 0.7, (rt, name, frac)
            pairs += len(rs)
            hits += frac * len(rs)
        for r in rs:  # most targets in every single room
            have = set(r.obj_category.tolist())
            share = np.mean([K.category_index(t) in have for t in K.TARGETS[rt]])
            assert share >= 0.7, (r.name, share)
    assert hits / pairs >= 0.9


def test_present_matches_room_objects(tiny_scenes):
    present = np.asarray(tiny_scenes.present)
    for n, sid in enumerate(np.asarray(tiny_scenes.scene_id).tolist()):
        r = layout.generate_room(tiny_scenes.meta("seed"), sid)
        want = np.zeros(K.NUM_CATEGORIES, bool)
        want[r.obj_category] = True
        np.testing.assert_array_equal(present[n], want, err_msg=f"FloorPlan{sid}")
        # visible only where present
        assert not np.asarray(tiny_scenes.visible)[tiny_scenes.state_slice(n)][:, ~want].any()


def test_small_objects_sit_near_their_anchors():
    """Pooled over rooms and categories: an anchored small object is much closer to its
    nearest anchor than to the nearest instance of the other categories in the room."""
    rooms = _rooms_of("kitchen", 10) + _rooms_of("living_room", 8) + _rooms_of("bedroom", 8)
    to_anchor, to_other = [], []
    per_cat: dict[str, tuple[list, list]] = {}
    for r in rooms:
        xz = r.obj_center[:, [0, 2]].astype(np.float64)
        cats = r.obj_category
        present = set(cats.tolist())
        for name, anchors in catalog.ANCHORS.items():
            c = K.category_index(name)
            a_idx = [K.category_index(a) for a in anchors]
            a_mask = np.isin(cats, a_idx)
            others = [o for o in present if o != c and o not in a_idx]
            if c not in present or not a_mask.any() or not others:
                continue
            for k in np.flatnonzero(cats == c):
                d_a = np.linalg.norm(xz[a_mask] - xz[k], axis=1).min()
                d_o = [np.linalg.norm(xz[cats == o] - xz[k], axis=1).min() for o in others]
                to_anchor.append(d_a)
                to_other.extend(d_o)
                per_cat.setdefault(name, ([], []))
                per_cat[name][0].append(d_a)
                per_cat[name][1].extend(d_o)
    assert len(to_anchor) >= 50
    ratio = np.mean(to_anchor) / np.mean(to_other)
    assert ratio < 0.6, ratio
    assert np.median(to_anchor) < 0.6 * np.median(to_other)
    assert len(per_cat) >= 8
    for name, (a, o) in per_cat.items():
        if len(a) >= 5:
            assert np.mean(a) < 0.85 * np.mean(o), (name, np.mean(a), np.mean(o))


def test_render_ascii(sample_rooms):
    r = sample_rooms[401]
    text = layout.render_ascii(r)
    rows = text.split("\n")
    assert len(rows) == r.wall.shape[0] and all(len(x) == r.wall.shape[1] for x in rows)
    assert rows[r.door[0]][r.door[1]] == "D"
    grid = np.array([list(x) for x in rows])
    assert set(np.unique(grid)) <= set("#=o.* D")
    # every reachable cell is '.' unless an object is drawn on it
    assert np.isin(grid[r.reachable], [".", "*"]).all()
    assert (grid[r.wall] != ".").all()


# ------------------------------------------------------------------ the co-occurrence knob

def _anchored(room) -> np.ndarray:
    """(K,) bool: the room's objects whose category has anchors (catalog.ANCHORS)."""
    return np.array([K.CATEGORIES[c] in catalog.ANCHORS for c in room.obj_category])


@pytest.mark.parametrize("floorplan", [1, 2, 201, 301, 302, 303])
def test_the_anchor_knob_moves_only_anchored_objects(floorplan):
    """Same seed, P = 0, 0.85, 1: the same walls, furniture, reachable cells and object
    list; objects without anchors in the same places; only anchored ones may move."""
    rooms = {p: layout.generate_room(0, floorplan, anchor_probability=p)
             for p in (0.0, 0.85, 1.0)}
    ref = rooms[0.85]                                   # the default: unchanged
    np.testing.assert_array_equal(ref.obj_center, layout.generate_room(0, floorplan).obj_center)
    anchored = _anchored(ref)
    for room in rooms.values():
        for field in ("wall", "furniture", "reachable", "obj_category", "block_height"):
            np.testing.assert_array_equal(getattr(room, field), getattr(ref, field), field)
        np.testing.assert_array_equal(room.obj_center[~anchored], ref.obj_center[~anchored])


def test_p1_puts_anchored_objects_by_an_anchor_and_p0_ignores_anchors():
    """Over the small preset's kitchens, living rooms and bedrooms: at P = 1 every
    anchored object whose room has an anchor sits within 1.75 m of one (at least 95%:
    a few rooms have no free surface near any);
    at P = 0 a clearly smaller share does (placement ignores anchors)."""
    CATEGORIES, ANCHORS, GRID_SIZE = K.CATEGORIES, catalog.ANCHORS, K.GRID_SIZE

    def share_near(p):
        near = total = 0
        for fp in [*range(1, 11), *range(201, 211), *range(301, 311)]:
            room = layout.generate_room(0, fp, anchor_probability=p)
            cats = [CATEGORIES[c] for c in room.obj_category]
            for k, name in enumerate(cats):
                anchors = [room.obj_center[j] for j, a in enumerate(cats)
                           if a in ANCHORS.get(name, ())]
                if not anchors:
                    continue
                d = min(np.hypot(*(room.obj_center[k][[0, 2]] - a[[0, 2]])) for a in anchors)
                near += d <= 1.5 + GRID_SIZE
                total += 1
        return near / total
    near1, near0 = share_near(1.0), share_near(0.0)
    assert near1 >= 0.95, near1          # (a few rooms have no free surface by one)
    assert near0 < near1 - 0.2, (near0, near1)


def test_scenes_build_records_the_anchor_probability(tmp_path, capsys):
    from orgnav_jax.scenes import load
    from orgnav_jax.scenes.__main__ import main as scenes_main
    out = tmp_path / "p0"
    assert scenes_main(["build", "--preset", "tiny", "--anchor-probability", "0",
                        "--out", str(out)]) == 0
    assert load(out).meta("anchor_probability") == 0.0
    capsys.readouterr()
    assert scenes_main(["info", str(out)]) == 0
    assert "anchor probability 0 " in capsys.readouterr().out
    with pytest.raises(ValueError, match="anchor_probability 1.5, expected 0 <= p <= 1"):
        scenes_main(["build", "--preset", "tiny", "--anchor-probability", "1.5",
                     "--out", str(tmp_path / "bad")])
