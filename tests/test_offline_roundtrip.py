"""Synthetic SceneSet -> authors' offline format -> SceneSet equals the original, up to
dtype (features are decoded to float32 on export, stored back as float16) and state
order (compared after mapping states by key); the CLI import saves a loadable set;
episodes survive JSON and pickle."""

from __future__ import annotations

import dataclasses
import json
import re

import h5py
import numpy as np
import pytest

from orgnav_jax import scenes as S
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.scenes.__main__ import main
from orgnav_jax.scenes.synthetic.builder import feature_bases, room_arrays, stack_rooms
from orgnav_jax.scenes.sceneset.keys import key_index, scene_state_keys
from orgnav_jax.scenes.offline.episodes import load_offline_episodes, write_offline_episodes
from orgnav_jax.scenes.offline import export_offline, import_offline
from orgnav_jax.scenes.offline.exporter import decoded_features
from orgnav_jax.scenes.synthetic.presets import get_preset

PER_STATE = ("next_state", "pose", "visible", "dist", "expert_action", "det_box", "det_conf")
PER_SCENE = ("present", "targets", "state_count", "room_type", "scene_id", "split")
OBJECT_ID = re.compile(r"^[A-Za-z]+\|[+-]\d\d\.\d\d\|[+-]\d\d\.\d\d\|[+-]\d\d\.\d\d$")


ROOMS = ((22, "test"), (401, "train"), (402, "train"), (421, "val"), (422, "test"))


@pytest.fixture(scope="module")
def original() -> S.SceneSet:
    """Five rooms of the tiny benchmark (FloorPlan22, a kitchen, and the four bathrooms:
    every split, two room types), built exactly as scenes.build("tiny", 0) builds them
    but without the other eleven rooms, to keep the tests fast."""
    rooms = [room_arrays(0, fp, split) for fp, split in ROOMS]
    return stack_rooms(rooms, info=(("preset", "tiny"), ("seed", 0)),
                       **feature_bases(get_preset("tiny")))


@pytest.fixture(scope="module")
def exported(original, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    report = export_offline(original, out)
    return out, report


@pytest.fixture(scope="module")
def imported(exported):
    return import_offline(exported[0])


def state_map(a: S.SceneSet, b: S.SceneSet, n: int) -> np.ndarray:
    """Local index in b's scene n of each state of a's scene n (matched by state key)."""
    ra, rb = a.state_slice(n), b.state_slice(n)
    ib = key_index(np.asarray(b.pose[rb]), rb.stop - rb.start)
    return np.array([ib[key] for key in scene_state_keys(np.asarray(a.pose[ra]),
                                                         ra.stop - ra.start)])


def assert_equal_by_key(a: S.SceneSet, b: S.SceneSet) -> None:
    assert a.scene_names == b.scene_names
    for f in PER_SCENE:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    for n in range(a.num_scenes):
        m = state_map(a, b, n)
        ra, rb = a.state_slice(n), b.state_slice(n)
        assert len(m) == ra.stop - ra.start == rb.stop - rb.start
        for f in PER_STATE:
            x, y = np.asarray(getattr(a, f)[ra]), np.asarray(getattr(b, f)[rb])[m]
            if f == "next_state":
                x, y = x - ra.start, y - rb.start    # global -> each room's own indices
                y = np.argsort(m)[y]  # b's state indices back into a's
            np.testing.assert_array_equal(x, y, err_msg=f"{a.scene_names[n]} {f}")


def test_round_trip_equals_original(original, imported):
    back, report = imported
    assert_equal_by_key(original, back)
    assert back.global_dim == original.global_dim and back.appearance_dim == original.appearance_dim
    for n in range(original.num_scenes):
        m = state_map(original, back, n) + back.state_slice(n).start     # global in back
        for lo, hi, glob, app in decoded_features(original, n):
            np.testing.assert_array_equal(back.global_feat[m[lo:hi]], glob.astype(np.float16))
            np.testing.assert_array_equal(back.appearance[m[lo:hi]], app.astype(np.float16))
    # the export decodes exactly as the model does (scenes.features.gather_features)
    glob, app, _, _ = S.gather_features(original, original.global_state(np.array([4, 4]),
                                                                         np.array([0, 100])))
    m = state_map(original, back, 4)[[0, 100]] + back.state_slice(4).start
    np.testing.assert_allclose(back.global_feat[m], np.asarray(glob), rtol=2e-3, atol=1e-3)
    np.testing.assert_allclose(back.appearance[m], np.asarray(app), rtol=2e-3, atol=1e-3)
    # our expert on the recovered graph agrees everywhere with the exported table
    opt = report["optimal_action"]
    assert opt["mismatches"] == 0 and opt["exact"] == opt["compared"] > 0
    assert all(r["ignored_edges"] == 0 and not r["ignored_types"] for r in report["scenes"])


def test_exported_files_follow_the_format(original, exported):
    out, report = exported
    assert report["scenes"] == 5 and report["states"] == int(original.state_count.sum())
    n = original.scene_names.index("FloorPlan401")
    k = int(original.state_count[n])
    keys = scene_state_keys(np.asarray(original.pose[original.state_slice(n)]), k)
    folder = out / "FloorPlan401"
    graph = json.loads((folder / "graph.json").read_text())
    assert graph["directed"] and [d["id"] for d in graph["nodes"]] == keys
    assert set(graph["links"][0]) == {"source", "target"}
    grid = json.loads((folder / "grid.json").read_text())
    assert {tuple(sorted(p)) for p in grid} == {("x", "y", "z")}
    assert len(grid) == k // 16
    vis = json.loads((folder / "visible_object_map_1.5.json").read_text())
    assert all(OBJECT_ID.match(oid) for oid in vis)
    present = np.flatnonzero(original.present[n])
    assert len(vis) == len(present)  # one synthetic object per present category
    with h5py.File(folder / "resnet18_featuremap.hdf5") as f:
        assert len(f) == k and f[keys[0]].shape == (1, original.global_dim, 7, 7)
        assert f[keys[0]].dtype == np.float32
    with h5py.File(folder / "fasterrcnn_features_22cls.hdf5") as f:
        assert len(f) == k and f[keys[0]].shape == (22, original.appearance_dim + 5)
    opt = json.loads((folder / "optimal_action.json").read_text())
    assert list(opt) == keys


def test_cli_import_saves_a_set_that_loads(exported, imported, tmp_path, capsys):
    out = tmp_path / "set"
    assert main(["import", "--offline-dir", str(exported[0]), "--out", str(out),
                 "--scenes", "FloorPlan401", "FloorPlan422", "--json"]) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["num_scenes"] == 2 and report["optimal_action"]["mismatches"] == 0
    loaded = S.load(out)
    want = imported[0]
    want = want.select([want.scene_names.index(n) for n in ("FloorPlan401", "FloorPlan422")])
    for f in dataclasses.fields(S.SceneSet):
        if f.name not in ("info",) and getattr(want, f.name) is not None:
            np.testing.assert_array_equal(getattr(loaded, f.name), getattr(want, f.name),
                                          err_msg=f.name)
    assert loaded.global_basis is None and loaded.meta("preset") == "offline"


def test_cli_errors_are_reported_not_raised(tmp_path, cli_error):
    assert "offline data directory does not exist" in cli_error(
        main, ["import", "--offline-dir", tmp_path / "nope", "--out", tmp_path / "o"])


def test_float16_hdf5_imports_identically(original, imported, tmp_path):
    one = original.select([original.scene_names.index("FloorPlan422")])
    export_offline(one, tmp_path, hdf5_dtype="float16")
    back, _ = import_offline(tmp_path)
    want = imported[0].select([imported[0].scene_names.index("FloorPlan422")])
    np.testing.assert_array_equal(back.global_feat, want.global_feat)
    np.testing.assert_array_equal(back.appearance, want.appearance)


def test_an_imported_set_exports_and_imports_unchanged(imported, tmp_path):
    """Raw features (bases None) are written as they are."""
    one = imported[0].select([imported[0].scene_names.index("FloorPlan421")])
    export_offline(one, tmp_path)
    again, report = import_offline(tmp_path)
    for f in dataclasses.fields(S.SceneSet):
        if f.name != "info" and getattr(one, f.name) is not None:
            np.testing.assert_array_equal(getattr(again, f.name), getattr(one, f.name),
                                          err_msg=f.name)
    assert report["optimal_action"]["mismatches"] == 0


@pytest.mark.parametrize("suffix", [".json", ".pkl"])
def test_episodes_round_trip(original, imported, tmp_path, suffix):
    back = imported[0]
    eps = sample_episodes(original, per_room_type=20, seed=3)
    path = write_offline_episodes(tmp_path / f"eps{suffix}", eps, original)
    got, skipped = load_offline_episodes(path, back)
    assert skipped == 0 and len(got) == len(eps)
    np.testing.assert_array_equal(got.scene, eps.scene)
    np.testing.assert_array_equal(got.target, eps.target)
    np.testing.assert_array_equal(got.optimal_len, eps.optimal_len)
    for n, s, t in zip(eps.scene, eps.start, got.start):
        assert t == state_map(original, back, n)[s]


def test_train_and_evaluate_on_an_imported_set_through_config(imported, tmp_path):
    """An imported set is a SceneSet directory like any other: `--scenes-dir` trains on
    it and `evaluate --scenes` evaluates on it."""
    from orgnav_jax import evaluate
    from orgnav_jax.training.config import get_config
    from orgnav_jax.training.loop import train
    S.save(imported[0], tmp_path / "thor")
    cfg = get_config("tiny", scenes_dir=str(tmp_path / "thor"), num_envs=8, rollout_len=4,
                     updates_per_chunk=1, total_env_steps=32, eval_episodes_per_room_type=2,
                     run_dir=str(tmp_path / "run"))
    out = train(cfg, progress=False)
    assert out["chunks"] == 1 and (tmp_path / "run" / "best").exists()
    res = evaluate.main(["--policy", "expert", "--split", "test", "--scenes",
                         str(tmp_path / "thor"), "--episodes-per-room-type", "5", "--quiet",
                         "--out", str(tmp_path / "expert.json")])
    assert res["overall"]["success"] == 1.0 and res["overall"]["episodes"] == 10
