"""Trial-driven imitation: which steps are supervised (il_step cause | state), with which
label, and how the loss is normalized (il_norm per_step | masked_mean); dropout masks
that the loss's replay rebuilds exactly."""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import env
from orgnav_jax.constants import DONE, MOVE_AHEAD, ROTATE_LEFT
from orgnav_jax.training.config import get_config
from orgnav_jax.training.losses import il_mask, imitation_loss, replay
from orgnav_jax.training.rollout import caused_deadlock


def test_imitation_loss_normalizations():
    logits = jnp.zeros((4, 2, 6))                       # uniform: CE = log 6 everywhere
    expert = jnp.array([[0, 1], [2, -1], [3, 4], [5, 0]], jnp.int32)
    mask = jnp.array([[1, 0], [1, 1], [0, 0], [1, 0]], jnp.float32)   # (1, 1) has no expert
    per_step, n = imitation_loss(logits, expert, mask, "per_step")
    mean, n2 = imitation_loss(logits, expert, mask, "masked_mean")
    assert float(n) == float(n2) == 3.0
    np.testing.assert_allclose(float(per_step), 3 * np.log(6) / 8, rtol=1e-6)
    np.testing.assert_allclose(float(mean), np.log(6), rtol=1e-6)
    zero, _ = imitation_loss(logits, expert, jnp.zeros_like(mask), "per_step")
    assert float(zero) == 0.0
    with pytest.raises(ValueError, match="unknown IL normalization 'sum'"):
        imitation_loss(logits, expert, mask, "sum")


def _handmade_episode(scenes):
    """A start state (scene, local index) where MoveAhead fails and the target is not in
    view; the scripted episode: MoveAhead (fails), 8 x RotateLeft (the 8th is back at the
    start pose: a loop), Done (premature)."""
    ns = np.asarray(scenes.next_state)
    for n in range(scenes.num_scenes):
        rows = scenes.state_slice(n)
        for s in range(rows.stop - rows.start):
            t = rows.start + s                     # global flat index
            if ns[t, MOVE_AHEAD] != t:
                continue
            cats = np.flatnonzero(np.asarray(scenes.targets[n]) &
                                  ~np.asarray(scenes.visible[t]))
            if cats.size:
                return n, s, int(cats[0])
    raise AssertionError("no start state with a wall ahead")


def test_cause_and_state_steps_and_labels_on_a_handmade_episode(tiny_scenes):
    scenes = tiny_scenes.split_view("train")
    n, s, c = _handmade_episode(scenes)
    params = env.EnvParams(step_caps=(30,) * 4)
    state = env.start_episode(n, s, c, scenes, params)
    actions = [MOVE_AHEAD] + [ROTATE_LEFT] * 8 + [DONE]
    deadlock, caused, failed, last_failed, expert, states = [], [], [], [], [], []
    for a in actions:
        obs = env.observe(state, scenes)
        deadlock.append(bool(obs.deadlock))
        last_failed.append(bool(state.last_failed))
        expert.append(int(scenes.expert_action[state.state, c]))
        states.append(int(state.state))
        _, state, _, done, info = env.step_env(state, jnp.int32(a), scenes, params)
        caused.append(bool(caused_deadlock(jnp.int32(a), info)))
        failed.append(bool(info["failed"]))
    assert bool(done) and not bool(info["success"])          # a premature Done
    assert states[1] == states[0] and states[9] == states[0]  # failed move; 8 turns = loop
    traj = types.SimpleNamespace(
        action=jnp.array(actions)[:, None],
        obs=types.SimpleNamespace(deadlock=jnp.array(deadlock)[:, None]),
        caused=jnp.array(caused)[:, None], failed=jnp.array(failed)[:, None],
        last_failed=jnp.array(last_failed)[:, None])
    cause = np.flatnonzero(np.asarray(il_mask("deadlock", "cause", traj))[:, 0])
    at_state = np.flatnonzero(np.asarray(il_mask("deadlock", "state", traj))[:, 0])
    # cause: the failing move, the turn that closed the loop, the premature Done
    assert cause.tolist() == [0, 8, 9]
    # state: the steps taken at the deadlock states (after the failure, after the loop)
    assert at_state.tolist() == [1, 9]
    assert np.flatnonzero(np.asarray(il_mask("failed", "cause", traj))[:, 0]).tolist() == [0]
    assert np.flatnonzero(np.asarray(il_mask("failed", "state", traj))[:, 0]).tolist() == [1]
    assert np.asarray(il_mask("all", "cause", traj)).sum() == len(actions)
    assert np.asarray(il_mask("none", "cause", traj)).sum() == 0
    # labels: the expert's action at the state where the supervised action was chosen;
    # the premature Done is corrected with a move (the target is not in view there)
    assert expert[9] != DONE and expert[9] >= 0
    logits = jnp.full((len(actions), 1, 6), -5.0).at[jnp.arange(len(actions)), 0,
                                                     jnp.array(expert)].set(5.0)
    loss, steps = imitation_loss(logits, jnp.array(expert)[:, None],
                                 il_mask("deadlock", "cause", traj), "per_step")
    assert float(steps) == 3 and float(loss) < 1e-3     # the expert's labels, not others


@pytest.mark.parametrize("dropout", [0.0, 0.25])
def test_replay_reproduces_the_rollout_with_and_without_dropout(tiny_scenes, dropout):
    """The loss's replay (non-recurrent part batched over T*N, recurrence scanned) equals
    the rollout's values, across episode resets, with the same dropout masks."""
    from orgnav_jax.models import build_model
    from orgnav_jax.training.rollout import rollout
    from orgnav_jax.training.update import env_params, init_runner, make_optimizer
    cfg = get_config("tiny", num_envs=8, rollout_len=24, episode_cap=6, lstm_layers=2,
                     dropout=dropout)
    train = tiny_scenes.split_view("train").to_device()
    model = build_model(cfg, train)
    runner = init_runner(cfg, model, make_optimizer(cfg), train, jax.random.PRNGKey(3))
    carry0 = runner.carry
    runner, traj, _, _ = rollout(model, runner, train, env_params(cfg), cfg.rollout_len,
                                 dropout)
    assert bool(traj.fresh[1:].any())                    # resets happen mid-rollout
    _, values = replay(model, runner.params, train, traj, carry0, dropout)
    np.testing.assert_allclose(np.asarray(values), np.asarray(traj.value), atol=1e-5)
    _, plain = replay(model, runner.params, train, traj.replace(drop_key=None), carry0)
    if dropout:
        assert np.abs(np.asarray(plain) - np.asarray(traj.value)).max() > 1e-3
    else:
        np.testing.assert_array_equal(np.asarray(plain), np.asarray(values))


def test_config_rejects_unknown_il_options_and_bad_dropout():
    with pytest.raises(ValueError, match="config field 'il_step': 'next'"):
        get_config("small", il_step="next")
    with pytest.raises(ValueError, match="config field 'il_norm'"):
        get_config("small", il_norm="sum")
    with pytest.raises(ValueError, match="config field 'dropout' must lie in"):
        get_config("small", dropout=1.0)


def test_version_2_runs_load_with_the_imitation_they_were_trained_with(tmp_path):
    import dataclasses
    import json

    from orgnav_jax.training.config import load_config
    doc = dataclasses.asdict(get_config("il"))
    for field in ("il_step", "il_norm"):
        doc.pop(field)
    doc["max_steps"] = doc.pop("episode_cap")         # its name before version 5
    (tmp_path / "config.json").write_text(json.dumps({"version": 2, **doc}))
    cfg = load_config(tmp_path)
    assert (cfg.il, cfg.il_step, cfg.il_norm) == ("deadlock", "state", "masked_mean")
    assert get_config("il").il_norm == "per_step"
