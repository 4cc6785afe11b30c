"""The evaluation protocol: SPL, episode files, expert and random policies, the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orgnav_jax import env, evaluate, evaluation
from orgnav_jax import episodes as E


@pytest.fixture(scope="module")
def test_split(tiny_scenes):
    return tiny_scenes.split_view("test").to_device()


@pytest.fixture(scope="module")
def test_episodes(test_split):
    return E.sample_episodes(test_split, seed=0, split="test")


def test_spl_hand_made_cases():
    success = np.array([1, 1, 0, 1, 1])
    path_len = np.array([4, 8, 3, 10, 2])
    optimal = np.array([4, 4, 3, 5, 2])
    np.testing.assert_allclose(evaluation.spl(success, path_len, optimal),
                               [1.0, 0.5, 0.0, 0.5, 1.0])
    per = {"success": success, "spl": evaluation.spl(success, path_len, optimal),
           "optimal_len": optimal}
    m = evaluation.summarize(per)
    assert m["success"] == pytest.approx(0.8) and m["spl"] == pytest.approx(0.6)
    assert m["episodes_L5"] == 1 and m["success_L5"] == 1.0 and m["spl_L5"] == 0.5


def test_episode_set_is_seeded_and_has_the_protocol_shape(test_split, test_episodes):
    again = E.sample_episodes(test_split, seed=0, split="test")
    other = E.sample_episodes(test_split, seed=1, split="test")
    np.testing.assert_array_equal(test_episodes.start, again.start)
    assert not np.array_equal(test_episodes.start, other.start)
    assert len(test_episodes) == 1000
    np.testing.assert_array_equal(np.bincount(test_episodes.room_type), [250] * 4)
    assert (test_episodes.optimal_len >= 1).all()
    targets = np.asarray(test_split.targets)
    assert targets[test_episodes.scene, test_episodes.target].all()


def test_episode_file_round_trip(tmp_path, test_split, test_episodes):
    path = tmp_path / "episodes.json"
    E.save_episodes(path, test_episodes, test_split)
    loaded = E.load_episodes(path, test_split)
    for f in ("scene", "start", "target", "optimal_len", "room_type"):
        np.testing.assert_array_equal(getattr(loaded, f), getattr(test_episodes, f))


def test_episode_file_for_other_scenes_is_a_clear_error(tmp_path, tiny_scenes, test_split,
                                                        test_episodes):
    path = tmp_path / "episodes.json"
    E.save_episodes(path, test_episodes, test_split)
    val = tiny_scenes.split_view("val")
    with pytest.raises(ValueError, match=r"names scene 'FloorPlan22', which is not in this "
                                         r"SceneSet.*made for other scenes"):
        E.load_episodes(path, val)
    doc = json.loads(path.read_text())
    doc["episodes"][0]["state"] = "99.00|99.00|0|0"
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"episode 0: state '99.00\|99.00\|0\|0' is not a "
                                         r"state of FloorPlan22"):
        E.load_episodes(path, test_split)
    doc["episodes"][0] = {"scene": "FloorPlan22", "goal_object_type": "Sofa", "state": "x"}
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="episode 0: unknown category 'Sofa'"):
        E.load_episodes(path, test_split)
    path.write_text("{not json")
    with pytest.raises(ValueError, match="is not valid JSON"):
        E.load_episodes(path, test_split)


def test_expert_succeeds_on_every_episode_with_spl_one(test_split, test_episodes):
    per = evaluation.run_episodes(evaluation.expert_policy(), None, test_split,
                                  test_episodes, env.EnvParams.evaluation(), batch_size=384)
    assert per["success"].all()
    np.testing.assert_array_equal(per["path_len"], test_episodes.optimal_len)
    np.testing.assert_allclose(per["spl"], 1.0)


def test_random_policy_is_low_and_reproducible(test_split, test_episodes):
    """Random (uniform over 6 actions, Done included) succeeds rarely: about 3% on the
    small benchmark's test split (README), and never needs more than a few steps."""
    a = evaluation.evaluate(evaluation.random_policy(), None, test_split, test_episodes, seed=3)
    b = evaluation.evaluate(evaluation.random_policy(), None, test_split, test_episodes, seed=3)
    assert a == b
    assert 0.0 < a["overall"]["success"] < 0.15
    assert a["overall"]["success_L5"] < 0.02
    assert set(a["per_room_type"]) == {"kitchen", "living_room", "bedroom", "bathroom"}


def test_evaluate_cli_writes_results_and_replays_episodes(tmp_path, tiny_scenes):
    from orgnav_jax.scenes import save
    scenes_dir = tmp_path / "tiny"
    save(tiny_scenes, scenes_dir)
    out = tmp_path / "expert.json"
    res = evaluate.main(["--policy", "expert", "--split", "val", "--scenes", str(scenes_dir),
                         "--out", str(out), "--quiet", "--episodes-per-room-type", "20"])
    assert res["overall"]["success"] == 1.0 and res["overall"]["episodes"] == 80
    saved = json.loads(out.read_text())
    assert saved["overall"] == res["overall"]
    replay = evaluate.main(["--policy", "random", "--split", "val", "--scenes",
                            str(scenes_dir), "--episodes", saved["episode_file"], "--quiet",
                            "--out", str(tmp_path / "random.json")])
    assert replay["overall"]["episodes"] == 80
