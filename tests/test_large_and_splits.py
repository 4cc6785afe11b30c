"""Issue 14: the real-size preset 'large' (AI2-THOR room sizes, raw features streamed to
disk) leaves the existing presets unchanged; `scenes import --splits FILE.json` gives
rooms of any name a split and a room type, then trains and evaluates; its bad inputs
are one-line errors naming the file and the room."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest

from orgnav_jax import scenes as S
from orgnav_jax.constants import ROOM_TYPES, SPLITS
from orgnav_jax.scenes.synthetic import layout
from orgnav_jax.scenes.__main__ import main
from orgnav_jax.scenes.synthetic.builder import feature_bases, room_arrays, stack_rooms
from orgnav_jax.scenes.sceneset.features import gather_features
from orgnav_jax.scenes.offline import export_offline
from orgnav_jax.scenes.synthetic.presets import get_preset

# ---------------------------------------------------------------- existing presets
# Fingerprints of the generator's output computed with the code before the 'large'
# preset (commit 5b9dd23): sha256 of the integer/bool tables, float64 sums of the float
# fields (pose, det_box, det_conf, appearance code, global code), per room.
PINNED_ROOMS = {
    (1, "train"): ["fdf09b2c7c51e721", 647080.0, 2829854.8886100203, 2855.8432620838284,
                   -3797.490131052069, 291532.3041654695],
    (22, "test"): ["f7ca5bbd9d2cb059", 425316.0, 3083121.12543346, 3194.965465426445,
                   962.4018503598163, 200025.78685166873],
    (201, "train"): ["365b35c3e0a49e38", 1030668.0, 5123997.834414408, 4976.586900949478,
                     2691.5640948044047, 421139.2780827638],
    (221, "val"): ["54ef81e12fa8d39a", 892404.0, 4282727.032479071, 4200.623638089746,
                   -5584.437302119938, 367636.526967885],
    (302, "train"): ["7e2073f404a2c02a", 398984.0, 1782833.1084231436, 1642.2465805783868,
                     363.27245880627197, 141482.15291934926],
    (322, "test"): ["e1b17f061fd2c6eb", 721528.0, 2795827.9661001116, 2478.62991136685,
                    904.1271850062521, 273057.7331415545],
    (401, "train"): ["1c38de5b85a59b64", 159836.0, 474675.97876398824, 433.60360434278846,
                     497.56239874399034, 51801.928351333365],
    (421, "val"): ["8d519d25d03c6f9d", 162676.0, 380968.3736894168, 331.2920306250453,
                   269.0019384609186, 49710.77873959206],
}
PINNED_BASES = {  # float64 sums of appearance_proto, appearance_basis, global_basis
    "tiny": [96.16671240516007, 2.6732379528693855, 5.3066211035475135],
    "small": [204.5383262161631, -1.8969976780936122, 18.784090693865437],
    "paper": [3428.6310369267558, 2.426085603554384, 58.36718581613968],
}
FLOAT_FIELDS = ("pose", "det_box", "det_conf", "appearance", "global_feat")


def _fingerprint(r) -> list:
    h = hashlib.sha256()
    for name in ("next_state", "visible", "present"):
        a = np.ascontiguousarray(getattr(r, name))
        h.update(f"{name}{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return [h.hexdigest()[:16]] + [float(np.asarray(getattr(r, n), np.float64).sum())
                                   for n in FLOAT_FIELDS]


@pytest.mark.parametrize("room", sorted(PINNED_ROOMS))
def test_default_rooms_are_unchanged(room):
    got, want = _fingerprint(room_arrays(0, *room)), PINNED_ROOMS[room]
    assert got[0] == want[0]
    np.testing.assert_allclose(got[1:], want[1:], rtol=1e-9)


def test_existing_presets_are_unchanged():
    for name, sums in PINNED_BASES.items():
        p = get_preset(name)
        assert (p.room_sizes, p.raw, p.num_rooms) == ("default", False, None)
        got = [float(np.float64(v).sum()) for v in feature_bases(p).values()]
        np.testing.assert_allclose(got, sums, rtol=1e-9)
        n_train, n_val, n_test = p.rooms_per_type
        want = [(base + k, t, split) for t, base in zip(ROOM_TYPES, (0, 200, 300, 400))
                for split, ks in (("train", range(1, n_train + 1)),
                                  ("val", range(21, 21 + 2 * n_val, 2)),
                                  ("test", range(22, 22 + 2 * n_test, 2)))
                for k in ks]
        assert p.floorplans() == want
    assert layout.ROOM_SIZE_PROFILES["default"] == (layout.ROOM_SIZE, layout.REACHABLE_RANGE)
    assert layout.REACHABLE_RANGE == {"kitchen": (60, 260), "living_room": (150, 380),
                                      "bedroom": (90, 320), "bathroom": (40, 120)}


# ---------------------------------------------------------------- the large preset
def test_large_room_sizes_are_ai2thor_like():
    """The 40 rooms of preset 'large' (val + test numbering): kitchens ~1,500 states,
    living rooms up to ~6,000, bathrooms ~1,000, bedrooms in between; ~80-90 k in all."""
    p = get_preset("large")
    counts = {t: [] for t in ROOM_TYPES}
    for fp, room_type, _ in p.floorplans():
        room = layout.generate_room(0, fp, room_sizes=p.room_sizes)
        counts[room_type].append(16 * int(room.reachable.sum()))
    mean = {t: np.mean(v) for t, v in counts.items()}
    assert all(len(v) == 10 for v in counts.values())
    assert 1200 <= mean["kitchen"] <= 1800 and max(counts["kitchen"]) <= 2300
    assert 800 <= mean["bathroom"] <= 1300 and max(counts["bathroom"]) <= 1600
    assert 5000 <= max(counts["living_room"]) <= 6200 and mean["living_room"] >= 3000
    assert mean["kitchen"] < mean["bedroom"] < mean["living_room"]
    assert 75_000 <= sum(map(sum, counts.values())) <= 95_000
    assert min(map(min, counts.values())) >= 16 * 36


def test_num_rooms_takes_every_type_and_split_in_turn():
    ten = get_preset("large", num_rooms=10).floorplans()
    assert len(ten) == 10 and {t for _, t, _ in ten} == set(ROOM_TYPES)
    assert {s for _, _, s in ten} == {"val", "test"}
    assert get_preset("large", num_rooms=40).floorplans() == get_preset("large").floorplans()
    train = get_preset("large", rooms_per_type=(5, 0, 0), num_rooms=20).floorplans()
    assert len(train) == 20 and {s for _, _, s in train} == {"train"}
    with pytest.raises(ValueError, match="num_rooms 41"):
        get_preset("large", num_rooms=41)


@pytest.fixture(scope="module")
def large4(tmp_path_factory):
    """Preset 'large' with 4 rooms at widths 8/8, built through the CLI."""
    out = tmp_path_factory.mktemp("large") / "set"
    assert main(["build", "--preset", "large", "--num-rooms", "4", "--global-dim", "8",
                 "--appearance-dim", "8", "--out", str(out)]) == 0
    return out


def test_large_is_stored_raw_like_an_import(large4):
    raw = S.load(large4)
    coded = S.build(get_preset("large", raw=False, num_rooms=4, global_dim=8,
                               appearance_dim=8))
    assert raw.global_basis is raw.appearance_basis is raw.appearance_proto is None
    assert raw.global_feat.dtype == raw.appearance.dtype == np.float16
    assert (raw.global_dim, raw.appearance_dim) == (8, 8)
    assert raw.meta("features") == "raw" and raw.meta("room_sizes") == "thor"
    assert raw.meta("preset") == "large" and raw.num_scenes == 4
    for name in ("next_state", "dist", "expert_action", "visible", "det_box", "det_conf",
                 "room_type", "scene_id", "split", "state_count", "targets"):
        np.testing.assert_array_equal(getattr(raw, name), getattr(coded, name), err_msg=name)
    # every state's features are float16 of what the coded set decodes to
    np.testing.assert_array_equal(raw.state_offset, coded.state_offset)
    state = np.arange(raw.num_states)                 # every flat state of the set
    for got, want in zip(gather_features(raw, state), gather_features(coded, state)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=2e-3, atol=1e-3)
    assert float(np.asarray(gather_features(raw, state)[0]).max()) > 0


def test_large_is_never_built_in_memory_or_in_the_cache(tmp_path, cli_error):
    with pytest.raises(ValueError, match="--out"):
        S.build("large")
    with pytest.raises(ValueError, match="not built into the cache"):
        S.load_or_build("large", cache_dir=tmp_path / "cache")
    assert not (tmp_path / "cache").exists()
    assert "num_rooms 0" in cli_error(main, ["build", "--preset", "large", "--num-rooms",
                                             "0", "--out", tmp_path / "o"])
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------- custom splits
ROOMS = ((1, "train"), (401, "train"), (421, "val"), (422, "test"))
RENAME = {"FloorPlan1": "kitchen_a", "FloorPlan401": "Bathroom-2"}
GOOD = {"kitchen_a": {"split": "train", "room_type": "Kitchen"},
        "Bathroom-2": {"split": "val", "room_type": "bathroom"},
        "FloorPlan421": "train", "FloorPlan422": "test"}


@pytest.fixture(scope="module")
def offline_dir(tmp_path_factory):
    """Four tiny rooms exported to the authors' format, two folders renamed so that
    they do not follow the FloorPlan numbering."""
    rooms = [room_arrays(0, fp, split) for fp, split in ROOMS]
    original = stack_rooms(rooms, info=(("preset", "tiny"), ("seed", 0)),
                           **feature_bases(get_preset("tiny")))
    out = tmp_path_factory.mktemp("offline")
    export_offline(original, out)
    for old, new in RENAME.items():
        shutil.move(out / old, out / new)
    (out / "orgnav_export.json").unlink()
    return out


def _write(path, text):
    path.write_text(text if isinstance(text, str) else json.dumps(text))
    return path


def test_import_with_splits_then_evaluate_and_train(offline_dir, tmp_path):
    from orgnav_jax import evaluate
    from orgnav_jax.training.config import get_config
    from orgnav_jax.training.loop import train
    splits = _write(tmp_path / "splits.json", GOOD)
    out = tmp_path / "set"
    assert main(["import", "--offline-dir", str(offline_dir), "--out", str(out),
                 "--splits", str(splits)]) == 0
    s = S.load(out)
    names = s.scene_names
    assert sorted(names) == sorted(GOOD)
    got = {n: (SPLITS[int(s.split[i])], ROOM_TYPES[int(s.room_type[i])])
           for i, n in enumerate(names)}
    assert got == {"kitchen_a": ("train", "kitchen"), "Bathroom-2": ("val", "bathroom"),
                   "FloorPlan421": ("train", "bathroom"), "FloorPlan422": ("test", "bathroom")}
    ids = dict(zip(names, np.asarray(s.scene_id).tolist()))
    assert ids["FloorPlan421"] == 421 and min(ids["kitchen_a"], ids["Bathroom-2"]) > 1000
    assert s.split_view("val").scene_names == ["Bathroom-2"]

    res = evaluate.main(["--policy", "expert", "--split", "val", "--scenes", str(out),
                         "--episodes-per-room-type", "5", "--quiet",
                         "--out", str(tmp_path / "expert.json")])
    assert res["overall"]["success"] == 1.0 and res["overall"]["episodes"] == 5
    cfg = get_config("tiny", scenes_dir=str(out), num_envs=8, rollout_len=4,
                     updates_per_chunk=1, total_env_steps=96, eval_episodes_per_room_type=2,
                     run_dir=str(tmp_path / "run"))
    assert train(cfg, progress=False)["chunks"] == 3


def test_only_listed_imports_just_the_named_rooms(offline_dir, tmp_path):
    splits = _write(tmp_path / "s.json", {"Bathroom-2": {"split": "val",
                                                         "room_type": "bathroom"},
                                          "FloorPlan422": "test"})
    out = tmp_path / "set"
    assert main(["import", "--offline-dir", str(offline_dir), "--out", str(out),
                 "--splits", str(splits), "--only-listed"]) == 0
    assert sorted(S.load(out).scene_names) == ["Bathroom-2", "FloorPlan422"]


BAD = {
    "unnamed": ({k: v for k, v in GOOD.items() if k != "FloorPlan422"},
                ["does not name", "'FloorPlan422'"]),
    "twice": ('{"kitchen_a": {"split": "train", "room_type": "kitchen"}, '
              '"Bathroom-2": {"split": "val", "room_type": "bathroom"}, '
              '"FloorPlan421": "train", "FloorPlan422": "test", "FloorPlan421": "val"}',
              ["'FloorPlan421' is named twice"]),
    "split": ({**GOOD, "FloorPlan422": "validation"},
              ["'FloorPlan422' has split 'validation'", "expected one of"]),
    "absent": ({**GOOD, "Garage": {"split": "test", "room_type": "kitchen"}},
               ["'Garage'", "not scene folders"]),
    "list": ('["kitchen_a", "train"]', ["holds a JSON list", "expected an object"]),
    "json": ('{"kitchen_a": "train",', ["not valid JSON"]),
    "no_type": ({**GOOD, "kitchen_a": "train"}, ["'kitchen_a' is not named FloorPlanN",
                                                  "room type must be given"]),
    "bad_type": ({**GOOD, "kitchen_a": {"split": "train", "room_type": "garage"}},
                 ["'kitchen_a' has room_type 'garage'"]),
    "bad_value": ({**GOOD, "FloorPlan421": 3}, ["'FloorPlan421' has split 3"]),
    "bad_keys": ({**GOOD, "FloorPlan421": {"split": "train", "type": "kitchen"}},
                 ["'FloorPlan421' maps to"]),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_splits_files_are_one_line_errors(case, offline_dir, tmp_path, cli_error):
    content, needles = BAD[case]
    splits = _write(tmp_path / f"{case}.json", content)
    msg = cli_error(main, ["import", "--offline-dir", offline_dir, "--out", tmp_path / "o",
                           "--splits", splits])
    assert str(splits) in msg, msg
    for needle in needles:
        assert needle in msg, msg
    assert not (tmp_path / "o").exists()


def test_other_splits_errors(offline_dir, tmp_path, cli_error):
    out = tmp_path / "o"
    assert "cannot read" in cli_error(main, ["import", "--offline-dir", offline_dir, "--out",
                                             out, "--splits", tmp_path / "missing.json"])
    assert "--only-listed needs --splits" in cli_error(
        main, ["import", "--offline-dir", offline_dir, "--out", out, "--only-listed"])
    # without --splits, FloorPlanN folders only; the renamed ones are pointed at
    only_custom = tmp_path / "custom"
    only_custom.mkdir()
    shutil.copytree(offline_dir / "kitchen_a", only_custom / "kitchen_a")
    msg = cli_error(main, ["import", "--offline-dir", only_custom, "--out", out])
    assert "no FloorPlanN scene folders" in msg and "--splits" in msg and "'kitchen_a'" in msg
    assert not out.exists()
