"""Bad scene inputs (issue 13, items 1, 5, 11): every case exits 2 with a one-line
`error: ...` naming the file, field, scene or state at fault, and changes or deletes
nothing that was there before.

Data: two hand-made offline rooms (test_offline_handmade.write_scene: FloorPlan401,
train; FloorPlan422, test), imported once; each case copies and corrupts that set.
"""

from __future__ import annotations

import hashlib
import pickle
import re
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from test_offline_handmade import START, write_scene

from orgnav_jax import evaluate
from orgnav_jax import scenes as S
from orgnav_jax.constants import CATEGORIES, DONE
from orgnav_jax.episodes import load_episodes
from orgnav_jax.scenes import UNREACHABLE
from orgnav_jax.scenes.__main__ import main
from orgnav_jax.scenes.offline.episodes import read_records
from orgnav_jax.scenes.offline import OfflineFormatError, import_offline
from orgnav_jax.scenes.offline.exporter import MARKER_FILE
from orgnav_jax.scenes.sceneset.storage import is_scene_set

NESTED = "[" * 100_000


def snapshot(root: Path) -> dict[str, str]:
    """Every file (its sha256) and directory under root, by relative path."""
    out = {}
    for p in sorted(Path(root).rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "<dir>"
    return out


@pytest.fixture(scope="module")
def offline(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("offline")
    write_scene(root)                      # FloorPlan401 (train)
    write_scene(root, "FloorPlan422")      # test split: `evaluate --split test` has a room
    return root


@pytest.fixture(scope="module")
def good(offline, tmp_path_factory) -> Path:
    """A valid saved SceneSet (the two rooms imported)."""
    path = tmp_path_factory.mktemp("good") / "set"
    S.save(import_offline(offline)[0], path)
    return path


@pytest.fixture
def copy_of(tmp_path):
    def copy(src: Path, name: str = "copy") -> Path:
        return Path(shutil.copytree(src, tmp_path / name))
    return copy


def foreign_dir(tmp_path: Path) -> Path:
    """A directory of someone else's files: a thesis and a sub-folder."""
    out = tmp_path / "mine"
    (out / "chapters").mkdir(parents=True)
    (out / "thesis.txt").write_text("four years of work\n")
    (out / "chapters" / "one.tex").write_text("\\chapter{One}\n")
    return out


def assert_unchanged(parent: Path, before: dict) -> None:
    assert snapshot(parent) == before  # nothing changed, deleted or left behind


# ------------------------------------------------------------------ --out protection
def out_argv(command: str, offline: Path, good: Path, out: Path) -> list:
    return {"import": ["import", "--offline-dir", offline, "--out", out],
            "build": ["build", "--preset", "tiny", "--out", out],
            "export": ["export", "--from", good, "--out", out],
            "export-preset": ["export", "--preset", "tiny", "--out", out]}[command]


@pytest.mark.parametrize("command", ["import", "build", "export", "export-preset"])
def test_out_refuses_a_directory_of_other_files(command, offline, good, tmp_path, cli_error):
    out = foreign_dir(tmp_path)
    before = snapshot(tmp_path)
    msg = cli_error(main, out_argv(command, offline, good, out))
    kind = "an offline export" if command.startswith("export") else "a SceneSet"
    assert re.fullmatch(rf"error: --out {re.escape(str(out))} is a non-empty directory that "
                        rf"is not {kind}.*; it is left untouched: choose another path", msg)
    assert_unchanged(tmp_path, before)


@pytest.mark.parametrize("command", ["import", "build"])
def test_out_refuses_a_scene_set_holding_a_user_file(command, offline, good, copy_of,
                                                     tmp_path, cli_error):
    out = copy_of(good)
    (out / "notes.txt").write_text("my notes\n")
    assert not is_scene_set(out)
    before = snapshot(tmp_path)
    msg = cli_error(main, out_argv(command, offline, good, out))
    assert f"--out {out} is a non-empty directory that is not a SceneSet" in msg
    assert_unchanged(tmp_path, before)
    with pytest.raises(FileExistsError, match="not a SceneSet"):  # the API refuses too
        S.save(S.load(good), out)
    assert_unchanged(tmp_path, before)


def test_out_refuses_a_file(offline, tmp_path, cli_error):
    out = tmp_path / "results.json"
    out.write_text("{}")
    msg = cli_error(main, ["import", "--offline-dir", offline, "--out", out])
    assert msg == (f"error: --out {out} is a file, expected a directory for a SceneSet; "
                   "nothing was written")
    assert out.read_text() == "{}"


def test_import_replaces_a_scene_set_of_ours(offline, good, copy_of, tmp_path):
    out = copy_of(good)
    assert is_scene_set(out)
    assert main(["import", "--offline-dir", str(offline), "--out", str(out),
                 "--scenes", "FloorPlan422"]) == 0
    assert S.load(out).scene_names == ["FloorPlan422"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy"]  # no temp or .old left


def test_save_keeps_a_foreign_dot_old_folder(good, copy_of, tmp_path):
    """The rename dance never deletes a pre-existing `.<name>.old` it did not write."""
    out = copy_of(good, "set")
    stray = tmp_path / ".set.old"
    stray.mkdir()
    (stray / "keep.txt").write_text("keep")
    S.save(S.load(good), out)
    assert (stray / "keep.txt").read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == [".set.old", "set"]


def test_export_replaces_its_own_export_only(good, tmp_path, cli_error):
    out = tmp_path / "exp"
    assert main(["export", "--from", str(good), "--out", str(out)]) == 0
    assert (out / MARKER_FILE).is_file()
    assert main(["export", "--from", str(good), "--out", str(out),
                 "--scenes", "FloorPlan401"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["FloorPlan401", "FloorPlan422",
                                                     MARKER_FILE]
    # a user file inside an exported scene folder: the folder is no longer ours
    (out / "FloorPlan401" / "my_labels.csv").write_text("a,b\n")
    before = snapshot(tmp_path)
    msg = cli_error(main, ["export", "--from", good, "--out", out])
    assert f"--out {out} is a non-empty directory that is not an offline export" in msg
    assert_unchanged(tmp_path, before)


def test_export_refuses_offline_data_it_did_not_write(offline, good, copy_of, tmp_path,
                                                      cli_error):
    """The authors' data (no marker file) is never overwritten by an export."""
    data = copy_of(offline, "authors")
    before = snapshot(tmp_path)
    msg = cli_error(main, ["export", "--from", good, "--out", data])
    assert "is a non-empty directory that is not an offline export of orgnav_jax" in msg
    assert_unchanged(tmp_path, before)


# ------------------------------------------------------------------ corrupt SceneSets
def _set(path: Path, field: str, fn) -> None:
    arr = np.load(path / f"{field}.npy")
    fn(arr)
    np.save(path / f"{field}.npy", arr)


def _flat(path: Path, n: int, s: int) -> int:
    """The flat index of scene n's local state s in a saved set."""
    return int(np.load(path / "state_offset.npy")[n]) + s


def _nan_appearance(path):
    t = _flat(path, 1, 7)
    _set(path, "appearance", lambda a: a.__setitem__((t, CATEGORIES.index("Sink"), 2), np.nan))


def _inf_global(path):
    t = _flat(path, 0, 5)
    _set(path, "global_feat", lambda a: a.__setitem__((t, 3, 4, 1), np.inf))


def _action_9(path):
    t = _flat(path, 0, 2)
    _set(path, "expert_action", lambda a: a.__setitem__((t, CATEGORIES.index("Sink")), 9))


def _disagree(path):
    """Replace one expert action (dist > 0) by a move that does not shorten the path."""
    dist = np.load(path / "dist.npy").astype(np.int64)       # (T, C), flat
    act = np.load(path / "expert_action.npy")
    nxt = np.load(path / "next_state.npy")                   # global flat indices
    c = CATEGORIES.index("Sink")
    for s in range(int(np.load(path / "state_count.npy")[0])):
        t = _flat(path, 0, s)
        d = dist[t, c]
        if 0 < d < UNREACHABLE:
            wrong = [m for m in range(DONE) if dist[nxt[t, m], c] != d - 1]
            if wrong:
                act[t, c] = wrong[0]
                np.save(path / "expert_action.npy", act)
                return s
    raise AssertionError("no state to corrupt")


def _next_out_of_range(path):
    t = _flat(path, 1, 4)
    _set(path, "next_state", lambda a: a.__setitem__((t, 0), 10_000))


def _confidence_37(path):
    t = _flat(path, 0, 3)
    _set(path, "det_conf", lambda a: a.__setitem__((t, CATEGORIES.index("Sink")), 37.5))


CORRUPT = {
    "nan-appearance": (_nan_appearance, r"field 'appearance' holds NaN at scene 1 "
                       r"\(FloorPlan422\) state 7 category Sink; expected finite values"),
    "inf-global_feat": (_inf_global, r"field 'global_feat' holds Inf at scene 0 "
                        r"\(FloorPlan401\) state 5; expected finite values"),
    "expert_action-9": (_action_9, r"field 'expert_action' holds 9 at scene 0 "
                        r"\(FloorPlan401\) state 2 target Sink; expected -1 \(NO_ACTION: no "
                        r"path\), 0\.\.4 \(the first move of a shortest path\) or 5 \(Done"),
    "dist-expert-disagree": (_disagree, r"fields 'expert_action' and 'dist' disagree at "
                             r"scene 0 \(FloorPlan401\) state \d+ target Sink: dist \d+, "
                             r"expert_action \w+ leads to state \d+ at dist \d+; expected \d+"),
    "next_state-out-of-range": (_next_out_of_range, r"field 'next_state' holds 10000 at "
                                r"scene 1 \(FloorPlan422\) state 4 action MoveAhead; "
                                r"expected a state of that scene \(flat indices "
                                r"\d+\.\.\d+\)"),
    # round five (issue 67): the ranges the format promises, not finiteness only
    "det_conf-37.5": (_confidence_37, r"field 'det_conf' holds 37\.5 at scene 0 "
                      r"\(FloorPlan401\) state 3 category Sink; expected detection "
                      r"confidences in \[0, 1\]"),
}


@pytest.mark.parametrize("case", list(CORRUPT))
def test_corrupt_set_is_refused_by_info_load_and_export(case, good, copy_of, tmp_path,
                                                        cli_error):
    corrupt, pattern = CORRUPT[case]
    path = copy_of(good)
    corrupt(path)
    before = snapshot(tmp_path)
    msg = cli_error(main, ["info", path])
    assert re.fullmatch(rf"error: {re.escape(str(path))}: {pattern}.*", msg), msg
    for mmap in (False, True):
        with pytest.raises(ValueError, match=pattern):
            S.load(path, mmap=mmap)
    msg = cli_error(main, ["export", "--from", path, "--out", tmp_path / "exp"])
    assert re.search(pattern, msg)
    assert_unchanged(tmp_path, before)


@pytest.mark.parametrize("case", ["nan-appearance", "expert_action-9"])
def test_evaluate_on_a_corrupt_set_fails_instead_of_scoring_zero(case, good, copy_of,
                                                                  tmp_path, cli_error):
    corrupt, pattern = CORRUPT[case]
    path = copy_of(good)
    corrupt(path)
    before = snapshot(tmp_path)
    msg = cli_error(evaluate.main, ["--policy", "expert", "--scenes", path, "--split", "test",
                                    "--quiet", "--out", tmp_path / "res.json"])
    assert re.search(pattern, msg)
    assert_unchanged(tmp_path, before)


def test_save_refuses_an_invalid_set(good, tmp_path):
    bad = S.load(good)
    bad = bad.replace(expert_action=np.where(np.asarray(bad.expert_action) == DONE, 9,
                                             bad.expert_action).astype(np.int8))
    with pytest.raises(ValueError, match="field 'expert_action' holds 9"):
        S.save(bad, tmp_path / "new")
    assert not (tmp_path / "new").exists() and list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ bad offline files
@pytest.mark.parametrize("file, row, pattern", [
    ("resnet18_featuremap.hdf5", None, rf"FloorPlan401/resnet18_featuremap\.hdf5 dataset "
     rf"{re.escape(repr(START))}: holds NaN; expected finite features"),
    ("fasterrcnn_features_22cls.hdf5", "Sink", r"FloorPlan401/fasterrcnn_features_22cls\.hdf5 "
     rf"dataset {re.escape(repr(START))}: row 18 \(Sink\) confidence holds Inf; expected "
     r"finite features"),
])
def test_import_rejects_non_finite_features(file, row, pattern, offline, copy_of, tmp_path,
                                            cli_error):
    data = copy_of(offline, "data")
    with h5py.File(data / "FloorPlan401" / file, "a") as f:
        arr = f[START][()]
        if row is None:
            arr[0, 1, 2, 3] = np.nan
        else:
            arr[CATEGORIES.index(row), -1] = np.inf
        f[START][...] = arr
    before = snapshot(tmp_path)
    msg = cli_error(main, ["import", "--offline-dir", data, "--out", tmp_path / "out"])
    assert re.search(pattern, msg), msg
    assert_unchanged(tmp_path, before)  # no --out written, offline data untouched


@pytest.mark.parametrize("file", ["graph.json", "visible_object_map_1.5.json",
                                  "optimal_action.json"])
def test_import_deeply_nested_json(file, offline, copy_of, tmp_path, cli_error):
    data = copy_of(offline, "data")
    (data / "FloorPlan401" / file).write_text(NESTED)
    before = snapshot(tmp_path)
    msg = cli_error(main, ["import", "--offline-dir", data, "--out", tmp_path / "out"])
    assert re.search(rf"FloorPlan401/{re.escape(file)}: JSON nested too deeply to read; "
                     r"expected ", msg), msg
    assert_unchanged(tmp_path, before)


def test_detection_classes_file_deeply_nested(offline, tmp_path, cli_error):
    classes = tmp_path / "classes.json"
    classes.write_text(NESTED)
    msg = cli_error(main, ["import", "--offline-dir", offline, "--out", tmp_path / "out",
                           "--detection-classes", classes])
    assert msg == (f"error: --detection-classes {classes}: JSON nested too deeply; expected "
                   "a JSON list of class names")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ bad episode files
def episode_argv(good: Path, episodes: Path, tmp_path: Path) -> list:
    return ["--policy", "expert", "--scenes", good, "--split", "test", "--quiet",
            "--episodes", episodes, "--out", tmp_path / "res.json"]


def test_deeply_nested_episode_file(good, tmp_path, cli_error):
    path = tmp_path / "eps.json"
    path.write_text(NESTED)
    before = snapshot(tmp_path)
    msg = cli_error(evaluate.main, episode_argv(good, path, tmp_path))
    assert msg.startswith(f"error: episode file {path}: JSON nested too deeply to read; "
                          "expected a JSON episode file")
    with pytest.raises(OfflineFormatError, match=r"eps\.json: JSON nested too deeply"):
        read_records(path)  # the authors'-form reader
    assert_unchanged(tmp_path, before)


@pytest.mark.parametrize("content, kind", [
    (pickle.dumps([{"scene": "FloorPlan422", "goal_object_type": "Sink", "state": START}],
                  protocol=2), "a Python pickle"),
    (bytes(range(256)) * 4, "binary data"),
])
def test_binary_episode_file(content, kind, good, tmp_path, cli_error):
    path = tmp_path / "eps.json"
    path.write_bytes(content)
    before = snapshot(tmp_path)
    msg = cli_error(evaluate.main, episode_argv(good, path, tmp_path))
    assert msg.startswith(f"error: episode file {path} is {kind}, not JSON text; expected a "
                          "JSON episode file")
    with pytest.raises(ValueError, match=re.escape(str(path))):
        load_episodes(path, S.load(good))
    assert_unchanged(tmp_path, before)



# ------------------------------------------------------------------ typed readers (issue 22)
def _edit_meta(path: Path, edit) -> None:
    import json
    meta = json.loads((path / "meta.json").read_text())
    edit(meta)
    (path / "meta.json").write_text(json.dumps(meta))


META_CASES = {
    "fields-list": (lambda m: m.update(fields=[]), r"meta\.json: field 'fields': expected an "
                    r"object \{field: \{'shape': \[\.\.\.\], 'dtype': \.\.\.\}\}, got a list"),
    "field-null": (lambda m: m["fields"].update(pose=None), r"meta\.json: fields\['pose'\]: "
                   r"expected an object \{'shape': \[int, \.\.\.\], 'dtype': str\}, got null"),
    "shape-string": (lambda m: m["fields"]["pose"].update(shape="big"),
                     r"meta\.json: fields\['pose'\]: field 'shape': expected a list of integers "
                     r">= 0, got 'big'"),
    "shape-float": (lambda m: m["fields"]["pose"].update(shape=[1e400, 4]),
                    r"meta\.json: fields\['pose'\]: field 'shape': expected a list of "
                    r"integers >= 0, got \[inf, 4\]"),
    "dtype-missing": (lambda m: m["fields"]["pose"].pop("dtype"),
                      r"meta\.json: fields\['pose'\]: field 'dtype' is missing"),
    "info-list": (lambda m: m.update(info=[1]), r"meta\.json: field 'info': expected an object "
                  r"\{key: value\}, got a list"),
    "info-nested": (lambda m: m["info"].update(preset={"a": 1}), r"meta\.json: info: field "
                    r"'preset': expected a string, number, boolean, null or a list of those"),
    "room-names": (lambda m: m["info"].update(room_name_ids=[1001], room_names=[7]),
                   r"meta\.json: info: field 'room_names': expected a list of 1 strings"),
    "version-float": (lambda m: m.update(version=2.0), r"meta\.json: format version 2\.0, "
                      r"this orgnav_jax reads versions 1 and 2"),
}


@pytest.mark.parametrize("case", list(META_CASES))
def test_a_malformed_meta_json_is_one_line_naming_file_and_field(case, good, copy_of,
                                                                 tmp_path, cli_error):
    edit, pattern = META_CASES[case]
    path = copy_of(good)
    _edit_meta(path, edit)
    before = snapshot(tmp_path)
    msg = cli_error(main, ["info", path])
    assert re.fullmatch(rf"error: {re.escape(str(path))}/{pattern}.*", msg), msg
    assert_unchanged(tmp_path, before)


@pytest.mark.parametrize("field", ["global_feat", "appearance"])
def test_a_set_of_zero_feature_channels_is_refused_on_load_and_save(field, good, copy_of,
                                                                    tmp_path, cli_error):
    path = copy_of(good)
    arr = np.load(path / f"{field}.npy")[..., :0]
    np.save(path / f"{field}.npy", arr)
    _edit_meta(path, lambda m: m["fields"][field].update(shape=list(arr.shape)))
    dim = {"global_feat": "global_dim", "appearance": "appearance_dim"}[field]
    pattern = rf"field '{field}' has 0 feature channels \({dim} 0\), expected at least 1"
    before = snapshot(tmp_path)
    assert re.search(pattern, cli_error(main, ["info", path]))
    assert_unchanged(tmp_path, before)
    full = S.load(good)
    with pytest.raises(ValueError, match=pattern):
        S.save(full.replace(**{field: np.asarray(getattr(full, field))[..., :0]}),
               tmp_path / "new")
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize("field, value, pattern", [
    ("seed", "1e400", r"field 'seed': expected an integer 0 <= seed <= 2,147,483,647, got inf"),
    ("seed", '"3"', r"field 'seed': expected an integer .*, got '3'"),
    ("seed", "null", r"field 'seed': expected an integer .*, got None"),
    ("seed", str(2 ** 40), r"field 'seed': expected an integer .*, got 1099511627776"),
    ("split", '["test"]', r"field 'split': expected one of \['', 'train', 'val', 'test'\], got "
                          r"\['test'\]"),
    ("scene", "[1]", r"episode 0: field 'scene': expected a string, got \[1\]"),
    ("optimal_len", "1e400", r"episode 0: field 'optimal_len': expected an integer 0 <= "
                             r"optimal_len <= 2,147,483,647, got inf"),
])
def test_an_episode_file_of_wrong_types_is_one_line(field, value, pattern, good, tmp_path,
                                                    cli_error):
    import json
    record = {"scene": "FloorPlan422", "goal_object_type": "Sink", "state": START}
    doc = {"format": "orgnav_jax.episodes/1", "split": "test", "seed": 0,
           "episodes": [record]}
    (record if field in record or field == "optimal_len" else doc)[field] = "@V@"
    path = tmp_path / "eps.json"
    path.write_text(json.dumps(doc).replace('"@V@"', value))
    before = snapshot(tmp_path)
    msg = cli_error(evaluate.main, episode_argv(good, path, tmp_path))
    assert re.fullmatch(rf"error: episode file {re.escape(str(path))}: {pattern}", msg), msg
    assert_unchanged(tmp_path, before)


def test_seeds_widths_and_floorplan_numbers_out_of_range_are_one_line(offline, copy_of,
                                                                       tmp_path, cli_error):
    """Issue 38 (round two's last two): `scenes info tiny --seed -1` names --seed before any
    build or progress bar; `build --global-dim 1000000000` (89 GB of projections) is
    refused before anything is built; a FloorPlan number beyond int32 in an offline import
    is named. Nothing is written."""
    for argv in (["info", "tiny", "--seed", "-1"], ["show", "1", "--seed", "-5"],
                 ["build", "--preset", "tiny", "--seed", "-1", "--out", tmp_path / "b"]):
        assert f"error: --seed {argv[argv.index('--seed') + 1]}: expected an integer 0 <= " \
               "seed" in cli_error(main, argv)
    line = cli_error(main, ["build", "--preset", "tiny", "--global-dim", "1000000000",
                            "--out", tmp_path / "b"])
    assert "global_dim 1000000000, expected 1..4096" in line, line
    assert not (tmp_path / "b").exists()
    src = copy_of(offline)
    (src / "FloorPlan422").rename(src / "FloorPlan99999999999")
    before = snapshot(tmp_path)
    line = cli_error(main, ["import", "--offline-dir", src, "--out", tmp_path / "o"])
    assert "'FloorPlan99999999999': FloorPlan number beyond 2,147,483,647" in line, line
    assert_unchanged(tmp_path, before)


# ------------------------------------------------------------------ round five (issue 67)
# The scene cache, checked against the preset's whole definition on every load. A
# 4-room preset (one train room per type, the tiny set's widths) stands in for
# `calibrated`; its "build" is a selection of the shared tiny set (no generation).
FOUR = "four"


@pytest.fixture
def four_cache(tiny_scenes, tmp_path, monkeypatch):
    """$ORGNAV_CACHE in tmp_path/cache, preset FOUR registered, build faked -> (path of
    its cache entry, the good set, the list of builds made)."""
    from orgnav_jax.scenes.synthetic import cache, presets
    from orgnav_jax.scenes.synthetic.builder import preset_info
    preset = presets.ScenePreset(FOUR, (2, 1, 1), global_dim=16, appearance_dim=16,
                                 num_rooms=4)
    monkeypatch.setitem(presets.SCENE_PRESETS, FOUR, preset)
    monkeypatch.setenv("ORGNAV_CACHE", str(tmp_path / "cache"))
    ids = np.asarray(tiny_scenes.scene_id).tolist()
    good = tiny_scenes.select([ids.index(fp) for fp, _, _ in preset.floorplans()])
    good = good.replace(info=preset_info(preset, 0))
    builds = []

    def fake_build(name, seed, progress=False):
        builds.append((name, seed))
        return good

    monkeypatch.setattr(cache, "build", fake_build)
    cache.clear_loaded()
    yield cache.cache_path(FOUR, 0), good, builds
    cache.clear_loaded()


def _perception_knob(path, good):
    _edit_meta(path, lambda m: m["info"].update({"perception.confusion": 0.2}))


def _fewer_rooms(path, good):      # a slot left by a test or an interrupted build
    S.save(good.select([0, 1]), path)


def _meta_gone(path, good):
    (path / "meta.json").unlink()


def _confidence_out_of_range(path, good):
    _confidence_37(path)


STALE = {
    "perception-knob": (_perception_knob, r"is not the set of preset 'four' seed 0 as "
                        r"defined now: perception\.confusion 0\.2, expected 0\.0 \(the "
                        r"default, not recorded\)"),
    "fewer-rooms": (_fewer_rooms, r"is not the set of preset 'four' seed 0 as defined "
                    r"now: 2 rooms, expected 4"),
    "meta-gone": (_meta_gone, r"is damaged \(meta\.json is missing\)"),
    "det_conf-37.5": (_confidence_out_of_range, r"is damaged \(.*field 'det_conf' holds "
                      r"37\.5 at scene 0 \(FloorPlan1\) state 3 category Sink"),
}


@pytest.mark.parametrize("case", list(STALE))
def test_a_cached_set_of_another_definition_or_damaged_is_rebuilt_in_place(
        case, four_cache, tmp_path, capsys):
    """Issue 67: a cached set whose info (perception knobs), rooms or values are not what
    the preset defines, or whose meta.json is gone, was used (or refused only after a
    rebuild, pointing at "another path"); it is rebuilt in place with a note naming why,
    and the next load uses the rebuilt set. Nothing outside the entry is touched."""
    from orgnav_jax.scenes.synthetic import cache
    path, good, builds = four_cache
    S.save(good, path)
    STALE[case][0](path, good)
    (tmp_path / "cache" / "mine.txt").write_text("a user's file beside the entry\n")
    capsys.readouterr()
    got = cache.load_or_build(FOUR, 0, progress=False, mmap=True)
    err = capsys.readouterr().err
    assert re.search(rf"note: the cached scene set {re.escape(str(path))} "
                     rf"{STALE[case][1]}.*: rebuilding it in place", err), err
    assert builds == [(FOUR, 0)] and got.num_scenes == 4
    assert cache.definition_mismatch(got, S.get_preset(FOUR), 0) == []
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["mine.txt", path.name]
    assert is_scene_set(path)
    cache.load_or_build(FOUR, 0, progress=False, mmap=True)
    assert builds == [(FOUR, 0)] and capsys.readouterr().err == ""


def test_a_cache_entry_holding_foreign_files_is_refused_naming_the_variable(
        four_cache, tmp_path, cli_error):
    """An entry that is not the program's own (a user's file in it) is refused before
    anything is built, naming $ORGNAV_CACHE; nothing is changed."""
    path, good, builds = four_cache
    S.save(good, path)
    (path / "meta.json").unlink()
    (path / "notes.txt").write_text("mine\n")
    before = snapshot(tmp_path)
    msg = cli_error(main, ["info", FOUR])
    assert msg == (f"error: scene cache entry {path} holds notes.txt, which this program "
                   "did not write: move them away, or set $ORGNAV_CACHE to another "
                   "directory"), msg
    assert builds == []
    assert_unchanged(tmp_path, before)


def test_a_perception_knob_given_twice_is_refused_and_summaries_show_the_knobs(
        tiny_scenes, tmp_path, cli_error):
    """`--perception confusion=0.1 confusion=0.2` took the last silently; no summary
    (`scenes build --json`, `scenes info`) showed any knob."""
    from orgnav_jax.scenes.summary import format_summary, summarize
    msg = cli_error(main, ["build", "--preset", "tiny", "--perception", "confusion=0.1",
                           "global_noise=0.5", "confusion=0.2", "--out", tmp_path / "b"])
    assert msg == ("error: perception knob confusion given twice ('confusion=0.1', "
                   "'confusion=0.2'): expected each knob once"), msg
    assert not (tmp_path / "b").exists()
    noisy = tiny_scenes.replace(info=tiny_scenes.info + (("perception.confusion", 0.2),))
    summary = summarize(noisy)
    assert summary["perception"]["confusion"] == 0.2
    assert summary["perception"]["peak_recall"] == 0.95          # every knob shown
    assert "perception: confusion 0.2 (other knobs at their defaults)" in \
        format_summary(summary)
    assert summarize(tiny_scenes)["perception"]["confusion"] == 0.0


def test_numpy_numbers_are_numbers_to_the_api():
    """np.float32(0.2) as a perception knob was refused as out of range; numpy numbers as
    preset or config fields reached json.dumps (a traceback when a set or run is saved)."""
    import json

    from orgnav_jax.scenes.synthetic.builder import preset_info
    from orgnav_jax.scenes.synthetic.perception import Perception
    from orgnav_jax.training.config import get_config
    knobs = Perception(global_noise=np.float32(0.2), min_box_area=np.int64(64))
    assert type(knobs.global_noise) is float and abs(knobs.global_noise - 0.2) < 1e-7
    preset = S.get_preset("tiny", rooms_per_type=(np.int64(2), 1, 1),
                          global_dim=np.int32(8), anchor_probability=np.float32(0.5),
                          perception=knobs)
    json.dumps(preset_info(preset, np.int64(3)))
    assert preset.rooms_per_type == (2, 1, 1) and type(preset.global_dim) is int
    with pytest.raises(ValueError, match=r"global_dim 8\.5, expected an integer"):
        S.get_preset("tiny", global_dim=8.5)
    cfg = get_config("tiny", lr=np.float32(1e-3), num_envs=np.int64(8))
    assert type(cfg.lr) is float and type(cfg.num_envs) is int
    assert json.loads(cfg.to_json())["num_envs"] == 8
