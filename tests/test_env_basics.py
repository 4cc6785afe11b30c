"""First environment tests: episode sampling, rewards, deadlock flags, the expert."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import env
from orgnav_jax.scenes import UNREACHABLE


@pytest.fixture(scope="module")
def train(tiny_scenes):
    return tiny_scenes.split_view("train").to_device()


def test_reset_samples_valid_episodes(train):
    params = env.EnvParams()
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    _, st = jax.vmap(env.reset, in_axes=(0, None, None))(keys, train, params)
    scene, state, target = map(np.asarray, (st.scene, st.state, st.target))
    assert np.asarray(train.targets)[scene, target].all()
    start = state - np.asarray(train.state_offset)[scene]    # EnvState.state is global
    assert ((start >= 0) & (start < np.asarray(train.state_count)[scene])).all()
    np.testing.assert_array_equal(train.state_scene[state], scene)
    d = np.asarray(train.dist)[state, target]
    assert (d >= 1).all() and (d < UNREACHABLE).all()
    np.testing.assert_array_equal(np.asarray(st.optimal_len), d)
    assert len(np.unique(scene)) == train.num_scenes  # every training room is drawn


def test_failed_move_and_revisit_are_deadlocks(train):
    params = env.EnvParams()
    nxt = np.asarray(train.next_state)
    n = 0
    rows = train.state_slice(n)
    blocked = np.flatnonzero(nxt[rows, K.MOVE_AHEAD] == np.arange(rows.start, rows.stop))
    start = int(blocked[0])                   # local index (as in an episode)
    target = int(np.flatnonzero(np.asarray(train.targets[n]))[0])
    st = env.start_episode(jnp.int32(n), jnp.int32(start), jnp.int32(target), train, params)
    obs, st, reward, done, info = env.step_env(st, K.MOVE_AHEAD, train, params)
    assert bool(info["failed"]) and bool(obs.deadlock) and not bool(done)
    assert int(st.state) == rows.start + start
    assert float(reward) == pytest.approx(params.step_penalty)
    # rotate left then right: back in a visited state -> revisit deadlock, not a failure
    obs, st, *_ = env.step_env(st, K.ROTATE_LEFT, train, params)
    assert not bool(obs.deadlock)
    obs, st, _, _, info = env.step_env(st, K.ROTATE_RIGHT, train, params)
    assert bool(obs.deadlock) and not bool(info["failed"])
    assert int(st.path_len) == 3 and int(st.steps) == 3


def test_episode_ends_at_the_cap(train):
    params = env.EnvParams(step_caps=(3, 3, 3, 3))
    _, st = env.reset(jax.random.PRNGKey(1), train, params)
    ends = []
    for _ in range(3):
        _, st, _, done, info = env.step_env(st, K.ROTATE_LEFT, train, params)
        ends.append((bool(done), bool(info["terminated"]), bool(info["truncated"])))
    assert ends == [(False, False, False)] * 2 + [(True, False, True)]   # cap: truncated


def test_done_is_terminated_never_truncated_even_on_the_last_step(train):
    params = env.EnvParams(step_caps=(3, 3, 3, 3))
    for before in (1, 2):            # Done before the cap, and as the cap's last step
        _, st = env.reset(jax.random.PRNGKey(1), train, params)
        for _ in range(before):
            _, st, *_ = env.step_env(st, K.ROTATE_LEFT, train, params)
        _, _, _, done, info = env.step_env(st, K.DONE, train, params)
        assert (bool(done), bool(info["terminated"]), bool(info["truncated"])) == \
            (True, True, False)


def test_expert_reaches_every_target_with_spl_one(train):
    params = env.EnvParams.evaluation()
    keys = jax.random.split(jax.random.PRNGKey(2), 64)
    _, st0 = jax.vmap(env.reset, in_axes=(0, None, None))(keys, train, params)

    def run(st):
        def body(carry, _):
            st, done, success, length = carry
            a = train.expert_action[st.state, st.target].astype(jnp.int32)
            _, st2, _, d, info = env.step_env(st, a, train, params)
            keep = lambda new, old: jnp.where(done, old, new)  # noqa: E731
            return (jax.tree_util.tree_map(keep, st2, st), done | d,
                    success | (info["success"] & ~done), keep(info["path_len"], length)), None
        init = (st, jnp.bool_(False), jnp.bool_(False), jnp.int32(0))
        return jax.lax.scan(body, init, None, length=100)[0]

    _, done, success, length = jax.jit(jax.vmap(run))(st0)
    assert np.asarray(done).all() and np.asarray(success).all()
    np.testing.assert_array_equal(np.asarray(length), np.asarray(st0.optimal_len))


def test_step_jit_equals_eager_and_vmap_equals_loop(train):
    params = env.EnvParams()
    keys = jax.random.split(jax.random.PRNGKey(3), 8)
    actions = jnp.arange(8) % K.NUM_ACTIONS
    _, st = jax.vmap(env.reset, in_axes=(0, None, None))(keys, train, params)
    batched = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None, None)),
                      static_argnums=4)(keys, st, actions, train, params)
    for i in range(8):
        one = jax.tree_util.tree_map(lambda x: x[i], st)
        eager = env.step(keys[i], one, actions[i], train, params)
        for a, b in zip(jax.tree_util.tree_leaves(eager), jax.tree_util.tree_leaves(batched)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[i])



def test_env_benchmark_computes_the_moves(train):
    """benchmarks/env_throughput.py times a program whose result needs every output of
    the step: change the transition table and its result changes. (When it returned
    only the finished count, XLA dropped the moves, the trail and the observations from
    the timed program, which looked 3x faster than the env.) Nothing is timed."""
    import sys
    from pathlib import Path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import env_throughput
    run = env_throughput.make_runner(train, env.EnvParams(), 8, 20)
    stay = jnp.broadcast_to(jnp.arange(train.next_state.shape[0])[:, None],
                            train.next_state.shape).astype(train.next_state.dtype)
    key = jax.random.PRNGKey(0)
    moved, stayed = run(key, train), run(key, train.replace(next_state=stay))
    assert float(moved[2]) != float(stayed[2])
