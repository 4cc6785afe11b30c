"""The JAX env against the plain-Python reference env; compile counts; bad input."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import env
from orgnav_jax.reference_env import ReferenceEnv
from orgnav_jax.scenes.sceneset.keys import state_key


@pytest.fixture(scope="module")
def scenes(tiny_scenes):
    return tiny_scenes.split_view("train").to_device()


@pytest.fixture(scope="module")
def reference(tiny_scenes):
    return ReferenceEnv.from_sceneset(tiny_scenes.split_view("train"))


@pytest.mark.parametrize("evaluation", [False, True])
def test_jax_env_agrees_with_reference_step_by_step(scenes, reference, evaluation):
    params = env.EnvParams.evaluation() if evaluation else env.EnvParams()
    reference.evaluation = evaluation
    rng = np.random.default_rng(int(evaluation))
    pose = np.asarray(scenes.pose)
    step = jax.jit(env.step_env, static_argnums=3)
    keys = jax.random.split(jax.random.PRNGKey(7), 12)
    compared = 0
    for k in keys:
        _, st = env.reset(k, scenes, params)
        n = int(st.scene)
        assert scenes.state_scene[int(st.state)] == n      # a global flat state of scene n
        obs_r = reference.reset(scenes.scene_names[n], state_key(pose[int(st.state)]),
                                K.CATEGORIES[int(st.target)])
        # mostly moves, some Done: episodes run long enough to hit caps and revisits
        p = np.array([0.46, 0.2, 0.2, 0.06, 0.06, 0.02])
        while True:
            a = int(rng.choice(K.NUM_ACTIONS, p=p))
            obs, st, reward, done, info = step(st, jnp.int32(a), scenes, params)
            obs_r, reward_r, done_r, success_r = reference.step(a)
            assert state_key(pose[int(st.state)]) == obs_r["state"]
            assert float(reward) == pytest.approx(reward_r)
            assert bool(done) == done_r and bool(info["success"]) == success_r
            assert bool(obs.deadlock) == obs_r["deadlock"]
            assert int(st.path_len) == reference.path_len
            for f in ("det_box", "det_conf", "target", "prev_action"):
                np.testing.assert_array_equal(np.asarray(getattr(obs, f)), obs_r[f])
            compared += 1
            if done_r:
                break
    assert compared > 150


def test_reference_successor_is_the_next_state_table(scenes, reference):
    """Recomputing successor poses from strings gives exactly the next_state table."""
    n = 1
    rows = scenes.state_slice(n)
    pose = np.asarray(scenes.pose)[rows]
    nxt = np.asarray(scenes.next_state)[rows] - rows.start      # global -> the room's own
    assert rows.start > 0 and (nxt >= 0).all() and (nxt < len(pose)).all()
    ref_scene = reference.scenes[scenes.scene_names[n]]
    for s in range(0, len(pose), 7):
        for a in range(K.NUM_ACTIONS - 1):
            assert ref_scene.successor(state_key(pose[s]), K.ACTIONS[a]) == \
                state_key(pose[nxt[s, a]])


def test_hot_functions_compile_once(scenes):
    params = env.EnvParams()
    step = jax.jit(chex.assert_max_traces(env.step, n=1), static_argnums=4)
    reset = jax.jit(chex.assert_max_traces(env.reset, n=1), static_argnums=2)
    _, st = reset(jax.random.PRNGKey(0), scenes, params)
    for i in range(5):
        _, st, *_ = step(jax.random.PRNGKey(i), st, jnp.int32(i % 6), scenes, params)
    _, st = reset(jax.random.PRNGKey(9), scenes, params)


def test_same_seed_same_episodes(scenes):
    params = env.EnvParams()
    keys = jax.random.split(jax.random.PRNGKey(5), 32)
    a = jax.vmap(env.reset, in_axes=(0, None, None))(keys, scenes, params)[1]
    b = jax.vmap(env.reset, in_axes=(0, None, None))(keys, scenes, params)[1]
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("action", [-1, 6, 17])
def test_action_out_of_range_is_a_clear_error(scenes, action):
    _, st = env.reset(jax.random.PRNGKey(0), scenes, env.EnvParams())
    with pytest.raises(ValueError, match=r"action .* expected integers in 0\.\.5"):
        env.step_env(st, action, scenes, env.EnvParams())
    with pytest.raises(ValueError, match="outside 0..5"):
        _reference_step(scenes, action)


def _reference_step(scenes, action):
    ref = ReferenceEnv.from_sceneset(scenes.select([0]))
    n = scenes.scene_names[0]
    ref.reset(n, sorted(ref.scenes[n].states)[0], "Sink")
    ref.step(action)


def test_target_the_scene_lacks_is_a_clear_error(scenes):
    targets = np.asarray(scenes.targets[0])
    missing = int(np.flatnonzero(~targets)[0])
    with pytest.raises(ValueError, match=rf"target {K.CATEGORIES[missing]} is not a valid "
                                         rf"target of {scenes.scene_names[0]}"):
        env.start_episode(jnp.int32(0), jnp.int32(0), jnp.int32(missing), scenes,
                          env.EnvParams())
    with pytest.raises(ValueError, match="start state"):
        env.start_episode(jnp.int32(0), jnp.int32(10 ** 6), jnp.int32(np.argmax(targets)),
                          scenes, env.EnvParams())
