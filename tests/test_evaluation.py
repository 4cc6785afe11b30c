"""The evaluation protocol: SPL, episode files, expert and random policies, the CLI."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import env, evaluate, evaluation
from orgnav_jax import episodes as E
from orgnav_jax.constants import DONE, LOOK_UP, ROTATE_LEFT


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
    # a start that sees its target: Done at once is the optimal path (1), a detour is 0
    np.testing.assert_allclose(evaluation.spl([1, 1, 0], [0, 3, 0], [0, 0, 0]), [1.0, 0.0, 0.0])
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


# ---- failure analysis: scripted policies with outcomes known from the env's semantics ----

def _constant_policy(name: str, action: int) -> evaluation.Policy:
    def act(_, carry, obs, key, scenes, fresh):
        return jnp.full(obs.state.shape, action, jnp.int32), carry
    return evaluation.Policy(name, lambda batch, _: (), act)


ALWAYS_DONE = _constant_policy("always Done", DONE)
ALWAYS_ROTATE = _constant_policy("always RotateLeft", ROTATE_LEFT)
ALWAYS_LOOK_UP = _constant_policy("always LookUp", LOOK_UP)
DONE_AT = 100  # the step at which ROTATE_THEN_DONE says Done: the kitchen cap


def _rotate_then_done_act(_, count, obs, key, scenes, fresh):
    count = jnp.where(fresh, 0, count) + 1                 # this step's number, 1-based
    return jnp.where(count >= DONE_AT, DONE, ROTATE_LEFT).astype(jnp.int32), count


ROTATE_THEN_DONE = evaluation.Policy(
    "RotateLeft x99, Done", lambda batch, _: jnp.zeros(batch, jnp.int32), _rotate_then_done_act)


@pytest.fixture(scope="module")
def few_episodes(test_split):
    return E.sample_episodes(test_split, 20, seed=0, split="test")


@pytest.fixture(scope="module")
def caps(test_split, few_episodes):
    return np.asarray(env.EnvParams.evaluation().step_caps)[few_episodes.room_type]


def _run(policy, split, episodes):
    return evaluation.run_episodes(policy, None, split, episodes, env.EnvParams.evaluation(),
                                   batch_size=len(episodes))


def _assert_partition(per):
    total = sum(per[k].astype(int) for k in evaluation.OUTCOMES)
    np.testing.assert_array_equal(total, 1)


def test_failure_analysis_of_always_done_is_a_wrong_done_at_the_start(test_split,
                                                                      few_episodes):
    """Episodes start at least one action from the target (never in view), so Done at
    the start is always a wrong Done, after one step and no move."""
    per = _run(ALWAYS_DONE, test_split, few_episodes)
    _assert_partition(per)
    assert per["wrong_done"].all() and not per["success"].any() and not per["timeout"].any()
    np.testing.assert_array_equal(per["steps"], 1)
    np.testing.assert_array_equal(per["revisits"], 0)
    np.testing.assert_array_equal(per["failed_moves"], 0)


def test_failure_analysis_of_always_rotate_left_counts_revisits(test_split, few_episodes,
                                                                caps):
    """8 headings: rotations 1..7 reach new states, rotation 8 is back at the start and
    every later one revisits a heading: cap - 7 revisits, no failed move, a timeout."""
    per = _run(ALWAYS_ROTATE, test_split, few_episodes)
    _assert_partition(per)
    assert per["timeout"].all()
    np.testing.assert_array_equal(per["steps"], caps)
    np.testing.assert_array_equal(per["revisits"], caps - 7)
    np.testing.assert_array_equal(per["failed_moves"], 0)


def test_failure_analysis_of_always_look_up_counts_failed_moves(test_split, few_episodes,
                                                                caps):
    """LookUp works only from horizon 30 (once, to 0), then fails on every step: failed
    moves are not counted as revisits although the agent stays on a visited state."""
    per = _run(ALWAYS_LOOK_UP, test_split, few_episodes)
    _assert_partition(per)
    assert per["timeout"].all()
    flat = np.asarray(test_split.global_state(few_episodes.scene, few_episodes.start))
    looking_down = np.asarray(test_split.pose)[flat, 3] == 30
    assert looking_down.any() and (~looking_down).any()
    np.testing.assert_array_equal(per["failed_moves"], caps - looking_down)
    np.testing.assert_array_equal(per["revisits"], 0)


def test_done_on_the_last_step_of_the_cap_is_not_a_timeout(test_split, few_episodes, caps):
    """99 RotateLefts, then Done at step 100: that is the kitchen cap, so the episode ends
    by Done and by the cap at once; it counts as success or wrong Done, never timeout.
    Success is known from the tables: the target visible after 99 mod 8 = 3 rotations."""
    per = _run(ROTATE_THEN_DONE, test_split, few_episodes)
    _assert_partition(per)
    assert not per["timeout"].any()
    np.testing.assert_array_equal(per["steps"], DONE_AT)
    next_state = np.asarray(test_split.next_state)          # global flat indices
    s = np.asarray(test_split.global_state(few_episodes.scene, few_episodes.start))
    for _ in range((DONE_AT - 1) % 8):
        s = next_state[s, ROTATE_LEFT]
    visible = np.asarray(test_split.visible)[s, few_episodes.target]
    np.testing.assert_array_equal(per["success"], visible)
    np.testing.assert_array_equal(per["wrong_done"], ~visible)
    np.testing.assert_array_equal(per["revisits"], DONE_AT - 1 - 7)
    assert (caps == DONE_AT).any()


def test_failure_analysis_of_the_expert_is_all_success(test_split, few_episodes):
    per = _run(evaluation.expert_policy(), test_split, few_episodes)
    _assert_partition(per)
    assert per["success"].all()
    np.testing.assert_array_equal(per["revisits"], 0)
    np.testing.assert_array_equal(per["failed_moves"], 0)


def test_failure_shares_sum_to_one_in_every_summary(test_split, test_episodes):
    res = evaluation.evaluate(evaluation.random_policy(), None, test_split, test_episodes,
                              seed=3)
    parts = [res["overall"], *res["per_room_type"].values(), *res["per_target"].values()]
    for m in parts:
        assert set(evaluation.FAILURE_KEYS) <= set(m)
        assert m["success"] + m["wrong_done"] + m["timeout"] == pytest.approx(1.0)
        assert m["revisits"] >= 0 and m["failed_moves"] >= 0
    assert res["overall"]["wrong_done"] > 0.5          # random says Done early and wrongly
    text = evaluation.format_failures({"Random": res["overall"], "old": {"success": 0.5}})
    assert "WrongDone" in text and text.splitlines()[-1].split()[1:] == ["50.0", "-", "-",
                                                                          "-", "-"]


def test_run_table_shows_failure_columns_and_dashes_for_old_results(tmp_path):
    from orgnav_jax.tables.table_files import write_table
    base = {"success": 0.4, "spl": 0.2, "success_L5": 0.3, "spl_L5": 0.1}
    new = {**base, "wrong_done": 0.25, "timeout": 0.35, "revisits": 3.0, "failed_moves": 1.5}
    new2 = {**new, "wrong_done": 0.35, "timeout": 0.25, "revisits": 5.0}
    text = write_table(tmp_path, {"baseline": {"0": new, "1": new2},
                                            "il": {"0": base, "1": new}})
    head, _, baseline, il = text.splitlines()
    assert head.split(" | ")[-4:] == ["wrong Done", "timeout", "revisits/ep",
                                      "failed moves/ep |"]
    assert baseline.split(" | ")[-4:] == ["30.0 ± 7.1", "30.0 ± 7.1", "4.0 ± 1.4",
                                          "1.5 ± 0.0 |"]          # sample std (ddof 1)
    assert il.split(" | ")[-4:] == ["-", "-", "-", "- |"]
    assert (tmp_path / "table.md").read_text() == text
