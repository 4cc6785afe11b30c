"""save/load round trips, views, and clear errors on bad input."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import scenes
from orgnav_jax.scenes.sceneset import storage
from orgnav_jax.scenes.synthetic.presets import ScenePreset, get_preset


def assert_same_sceneset(a: scenes.SceneSet, b: scenes.SceneSet) -> None:
    for f in dataclasses.fields(scenes.SceneSet):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if f.name == "info":
            assert tuple(x) == tuple(y)
            continue
        if x is None or y is None:
            assert x is None and y is None, f.name
            continue
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype, (f.name, x.dtype, y.dtype)
        assert x.shape == y.shape, (f.name, x.shape, y.shape)
        if not np.array_equal(x, y):  # (fast path; assert_array_equal is slow on float16)
            np.testing.assert_array_equal(x, y, err_msg=f.name)


@pytest.fixture(scope="module")
def bath(tiny_scenes) -> scenes.SceneSet:
    """The 4 bathrooms of the tiny set: a small SceneSet for the error paths."""
    return tiny_scenes.room_type_view("bathroom")


@pytest.fixture
def saved(bath, tmp_path):
    return scenes.save(bath, tmp_path / "bath")


# ------------------------------------------------------------------ round trips
def test_round_trip_full_tiny_set(tiny_scenes, tmp_path):
    path = scenes.save(tiny_scenes, tmp_path / "tiny")
    assert (path / storage.META_FILE).exists()
    back = scenes.load(path)
    assert_same_sceneset(tiny_scenes, back)
    assert back.meta("preset") == "tiny" and back.meta("seed") == 0
    assert back.meta("rooms_per_type") == (2, 1, 1)
    assert scenes.disk_size(path) > 0
    # memory-mapped loading gives the same arrays
    assert_same_sceneset(tiny_scenes, scenes.load(path, mmap=True))


def test_round_trip_subset_and_meta_file_path(bath, saved):
    assert_same_sceneset(bath, scenes.load(saved))
    assert_same_sceneset(bath, scenes.load(saved / storage.META_FILE))
    assert_same_sceneset(bath, scenes.load(str(saved)))


def test_save_replaces_existing_set(tiny_scenes, bath, tmp_path):
    path = tmp_path / "set"
    scenes.save(bath, path)
    other = tiny_scenes.room_type_view("kitchen")
    scenes.save(other, path)
    assert_same_sceneset(other, scenes.load(path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["set"]  # no temp leftovers


# ------------------------------------------------------------------------- views
def test_split_view_only_that_split(tiny_scenes):
    full_ids = np.asarray(tiny_scenes.scene_id).tolist()
    for name in K.SPLITS:
        v = tiny_scenes.split_view(name)
        want = [sid for sid, sp in zip(full_ids, np.asarray(tiny_scenes.split))
                if sp == K.SPLIT_INDEX[name]]
        assert np.asarray(v.scene_id).tolist() == want
        assert (np.asarray(v.split) == K.SPLIT_INDEX[name]).all()
        counts = np.asarray(v.state_count)
        assert v.num_states == counts.sum()            # only its own rooms' states
        v.validate(f"split_view({name})")
        for n, sid in enumerate(want):
            m = full_ids.index(sid)
            rv, rf = v.state_slice(n), tiny_scenes.state_slice(m)
            assert rv.stop - rv.start == rf.stop - rf.start == counts[n]
            for f in ("next_state", "visible", "dist", "expert_action", "det_conf"):
                x = np.asarray(getattr(v, f))[rv]
                y = np.asarray(getattr(tiny_scenes, f))[rf]
                if f == "next_state":                  # global indices, re-based
                    x, y = x - rv.start, y - rf.start
                np.testing.assert_array_equal(x, y, err_msg=f)
            np.testing.assert_array_equal(np.asarray(v.present)[n],
                                          np.asarray(tiny_scenes.present)[m])
    with pytest.raises(ValueError, match="nope"):
        tiny_scenes.split_view("nope")


def test_val_split_scene_ids(tiny_scenes):
    v = tiny_scenes.split_view("val")
    ids = np.asarray(v.scene_id)
    assert len(ids) == 4
    assert all((int(i) % 100) % 2 == 1 and 21 <= int(i) % 100 <= 29 for i in ids)


# -------------------------------------------------------------- bad arguments
def test_build_unknown_preset():
    with pytest.raises(ValueError, match="'nope'"):
        scenes.build("nope")


def test_get_preset_errors():
    with pytest.raises(ValueError, match="bogus_field"):
        get_preset("tiny", bogus_field=3)
    with pytest.raises(ValueError, match="bogus_field"):
        scenes.build("tiny", bogus_field=3)
    with pytest.raises(ValueError, match="'nope'"):
        get_preset("nope")
    with pytest.raises(ValueError, match="train"):
        ScenePreset("x", rooms_per_type=(21, 0, 0))
    with pytest.raises(ValueError, match="global_dim"):
        get_preset("tiny", global_dim=0)
    p = get_preset("tiny", appearance_dim=7)
    assert p.appearance_dim == 7 and p.global_dim == get_preset("tiny").global_dim


def test_unknown_names_rejected():
    with pytest.raises(ValueError, match="Spoon"):
        K.category_index("Spoon")
    with pytest.raises(ValueError, match="garage"):
        K.room_type_index("garage")
    with pytest.raises(ValueError, match="holdout"):
        K.split_index("holdout")
    assert K.category_index("Toaster") == K.CATEGORIES.index("Toaster")


# ------------------------------------------------------------------- bad files
def test_load_nonexistent_path(tmp_path):
    path = tmp_path / "no_such_set"
    with pytest.raises(FileNotFoundError, match=re.escape(str(path))):
        scenes.load(path)


def test_load_plain_file(tmp_path):
    path = tmp_path / "scenes.txt"
    path.write_text("hello")
    with pytest.raises(ValueError, match=re.escape(str(path))):
        scenes.load(path)


def test_load_directory_without_meta(tmp_path):
    path = tmp_path / "empty"
    path.mkdir()
    with pytest.raises(ValueError, match=re.escape(storage.META_FILE)):
        scenes.load(path)


def _edit_meta(path, **changes):
    meta_path = path / storage.META_FILE
    meta = json.loads(meta_path.read_text())
    meta.update(changes)
    meta_path.write_text(json.dumps(meta))
    return meta


def test_load_foreign_format(saved):
    _edit_meta(saved, format="someone.elses.format")
    with pytest.raises(ValueError, match="someone.elses.format"):
        scenes.load(saved)


def test_load_other_version(saved):
    _edit_meta(saved, version=999)
    with pytest.raises(ValueError, match="999"):
        scenes.load(saved)


def test_load_meta_not_json(saved):
    (saved / storage.META_FILE).write_text("{not json")
    with pytest.raises(ValueError, match=re.escape(storage.META_FILE)):
        scenes.load(saved)


@pytest.mark.parametrize("field", ["dist", "global_feat", "next_state"])
def test_load_truncated_npy(saved, field):
    file = saved / f"{field}.npy"
    data = file.read_bytes()
    file.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=re.escape(file.name)):
        scenes.load(saved)


def test_load_truncated_header(saved):
    file = saved / "pose.npy"
    file.write_bytes(file.read_bytes()[:20])
    with pytest.raises(ValueError, match="pose"):
        scenes.load(saved)


def test_load_npy_wrong_shape_against_meta(saved):
    file = saved / "dist.npy"
    arr = np.load(file)
    np.save(file, arr[:, :-1])
    with pytest.raises(ValueError, match=r"dist\.npy.*shape"):
        scenes.load(saved)


def test_load_npy_wrong_shape_consistent_meta(saved):
    """A file whose shape matches meta.json but not the other fields: validate names it."""
    file = saved / "dist.npy"
    arr = np.load(file)[..., :-1]
    np.save(file, arr)
    meta = json.loads((saved / storage.META_FILE).read_text())
    meta["fields"]["dist"]["shape"] = list(arr.shape)
    (saved / storage.META_FILE).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="'dist'"):
        scenes.load(saved)


def test_load_wrong_dtype(saved):
    file = saved / "det_conf.npy"
    np.save(file, np.load(file).astype(np.float64))
    with pytest.raises(ValueError, match=r"det_conf"):
        scenes.load(saved)


def test_load_missing_npy_file(saved):
    (saved / "visible.npy").unlink()
    with pytest.raises(ValueError, match=r"visible\.npy"):
        scenes.load(saved)


def test_load_field_missing_from_meta(saved):
    meta = json.loads((saved / storage.META_FILE).read_text())
    del meta["fields"]["expert_action"]
    (saved / storage.META_FILE).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="expert_action"):
        scenes.load(saved)


def test_interrupted_save_keeps_previous_set(tiny_scenes, bath, saved, monkeypatch):
    before = sorted(p.name for p in saved.parent.iterdir())
    real_save = np.save
    calls = []

    def flaky_save(file, arr, *args, **kwargs):
        calls.append(str(file))
        if len(calls) == 4:
            raise OSError("disk full (simulated)")
        return real_save(file, arr, *args, **kwargs)

    monkeypatch.setattr(np, "save", flaky_save)
    other = tiny_scenes.room_type_view("kitchen")
    with pytest.raises(OSError, match="simulated"):
        scenes.save(other, saved)
    monkeypatch.undo()
    assert len(calls) == 4
    assert sorted(p.name for p in saved.parent.iterdir()) == before  # temp dir removed
    assert_same_sceneset(bath, scenes.load(saved))


def test_interrupted_first_save_leaves_nothing(bath, tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "save", boom)
    with pytest.raises(KeyboardInterrupt):
        scenes.save(bath, tmp_path / "new")
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(FileNotFoundError):
        scenes.load(tmp_path / "new")


def test_save_interrupted_between_renames_keeps_previous_set(tiny_scenes, bath, saved,
                                                             monkeypatch):
    from pathlib import Path
    real_rename = Path.rename
    calls = []

    def flaky_rename(self, target):
        calls.append((self.name, Path(target).name))
        if len(calls) == 2:                     # tmp -> path
            raise KeyboardInterrupt
        return real_rename(self, target)

    monkeypatch.setattr(Path, "rename", flaky_rename)
    with pytest.raises(KeyboardInterrupt):
        scenes.save(tiny_scenes.room_type_view("kitchen"), saved)
    monkeypatch.undo()
    assert calls[0] == (saved.name, f".{saved.name}.old")
    assert_same_sceneset(bath, scenes.load(saved))


def test_select_errors(tiny_scenes):
    with pytest.raises(ValueError, match="empty"):
        tiny_scenes.select(np.zeros(tiny_scenes.num_scenes, bool))
    with pytest.raises(ValueError, match="garage"):
        tiny_scenes.room_type_view("garage")
    v = tiny_scenes.select([3, 0])
    assert np.asarray(v.scene_id).tolist() == np.asarray(tiny_scenes.scene_id)[[3, 0]].tolist()
    v.validate("select([3, 0])")
    for n, m in enumerate((3, 0)):
        np.testing.assert_array_equal(np.asarray(v.pose)[v.state_slice(n)],
                                      np.asarray(tiny_scenes.pose)[tiny_scenes.state_slice(m)])
    assert v.info == tiny_scenes.info
    assert v.global_basis is tiny_scenes.global_basis


def test_load_or_build_keeps_a_set_another_process_saved_meanwhile(bath, tmp_path,
                                                                   monkeypatch):
    """Two processes building the same cached set: the second to finish keeps the first's
    files (same inode: never renamed away under a process reading them) and loads them;
    an explicit save still replaces."""
    from orgnav_jax.scenes.synthetic import cache
    monkeypatch.setenv("ORGNAV_CACHE", str(tmp_path / "cache"))
    path = cache.cache_path("tiny", 3)

    inodes = []

    def racing_build(preset, seed, progress=False):     # the other process saves first
        storage.save(bath, path)
        inodes.append((path / storage.META_FILE).stat().st_ino)
        return bath

    monkeypatch.setattr(cache, "build", racing_build)
    got = cache.load_or_build("tiny", 3, progress=False, mmap=True)
    inode = (path / storage.META_FILE).stat().st_ino
    assert inode == inodes[0]
    assert_same_sceneset(got, bath)
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]   # no temp left
    storage.save(bath, path)
    assert (path / storage.META_FILE).stat().st_ino != inode


def tiny_of_seed(tiny_scenes, seed: int) -> scenes.SceneSet:
    """tiny_scenes recorded as the tiny set of `seed` (what the cache checks: the info,
    widths and rooms; a stand-in for building it)."""
    from orgnav_jax.scenes.synthetic.builder import preset_info
    return tiny_scenes.replace(info=preset_info(get_preset("tiny"), seed))


def test_load_or_build_caches(tiny_scenes, tmp_path, monkeypatch):
    from orgnav_jax.scenes.synthetic import cache
    calls = []

    def fake_build(preset, seed, progress=False):
        calls.append((preset, seed))
        return tiny_of_seed(tiny_scenes, seed)

    monkeypatch.setattr(cache, "build", fake_build)
    monkeypatch.setenv("ORGNAV_CACHE", str(tmp_path / "cache"))
    first = scenes.load_or_build("tiny", 3, progress=False)
    second = scenes.load_or_build("tiny", 3, progress=False)
    assert calls == [("tiny", 3)]
    assert_same_sceneset(first, second)
    assert (tmp_path / "cache" / f"scenes-tiny-seed3-v{storage.FORMAT_VERSION}"
            / storage.META_FILE).exists()       # keyed by format version: a new one rebuilds
    scenes.load_or_build("tiny", 4, progress=False)
    assert calls == [("tiny", 3), ("tiny", 4)]
