"""orgnav_jax.gymnax_env: NavEnv is orgnav_jax.env as a gymnax Environment (same numbers),
its observation is the model's decoded input, gymnax's wrappers and the gymnasium bridges
run on it, and (slow) the PPO of examples/ppo_gymnax.py learns on the tiny rooms."""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnax import wrappers

from orgnav_jax import env as nav
from orgnav_jax import gymnax_env
from orgnav_jax.models import model_inputs

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "ppo_gymnax.py"


@pytest.fixture(scope="module")
def train_rooms(tiny_scenes):
    """The tiny set's train split on the device (shared by the env and the reference)."""
    return tiny_scenes.split_view("train").to_device()


@pytest.fixture(scope="module")
def flat_env(train_rooms):
    env = gymnax_env.NavEnv("flat", max_steps=30,
                            default_params=gymnax_env.make_params(train_rooms))
    return env, env.default_params


def same(a, b) -> bool:
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in
               zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True))


def flat_inputs(rooms, obs: nav.Observation) -> np.ndarray:
    """The model's decoded inputs of a batch of env observations, flattened per env."""
    x = model_inputs(rooms, obs)
    parts = (x.glob, x.app, x.box, x.conf, x.target, x.prev_action)
    return np.concatenate([np.asarray(p).reshape(p.shape[0], -1) for p in parts], -1)


def test_step_equals_env_step_and_obs_is_the_models_input(flat_env, train_rooms):
    """8 envs, 70 steps of random actions (Done included, so episodes end both ways and
    auto-reset): state, reward, terminated/truncated and info equal orgnav_jax.env.step's
    for the same key, state and action; the flat observation is model_inputs flattened."""
    env, params = flat_env
    rules = nav.EnvParams()
    B = 8
    reset = jax.jit(jax.vmap(env.reset, (0, None)))
    step = jax.jit(jax.vmap(env.step, (0, 0, 0, None)))
    ref_step = jax.jit(jax.vmap(lambda k, s, a: nav.step(k, s, a, train_rooms, rules)))
    ref_reset = jax.jit(jax.vmap(lambda k: nav.reset(k, train_rooms, rules)))
    key = jax.random.PRNGKey(3)
    keys = jax.random.split(key, B)
    obs, state = reset(keys, params)
    ref_obs, ref_state = ref_reset(keys)
    assert same(state, ref_state)
    np.testing.assert_array_equal(np.asarray(obs), flat_inputs(train_rooms, ref_obs))
    ended = {"terminated": 0, "truncated": 0}
    for t in range(70):
        key, k_act, k_env = jax.random.split(key, 3)
        action = jax.random.randint(k_act, (B,), 0, 6)
        action = jnp.where(jax.random.uniform(k_act, (B,)) < 0.9, action % 5, action)  # Done rarer
        keys = jax.random.split(k_env, B)
        obs, new, reward, term, trunc, info = step(keys, state, action, params)
        ref_obs, ref_new, ref_reward, ref_done, ref_info = ref_step(keys, state, action)
        assert same(new, ref_new), t
        np.testing.assert_array_equal(np.asarray(obs), flat_inputs(train_rooms, ref_obs))
        np.testing.assert_array_equal(reward, ref_reward)
        np.testing.assert_array_equal(term | trunc, ref_done)
        for k, v in ref_info.items():
            np.testing.assert_array_equal(info[k], v, err_msg=k)
        np.testing.assert_array_equal(term, ref_info["terminated"])
        np.testing.assert_array_equal(trunc, ref_info["truncated"])
        assert not np.any(np.asarray(term & trunc))
        ended["terminated"] += int(term.sum())
        ended["truncated"] += int(trunc.sum())
        state = new
    assert ended["terminated"] > 0 and ended["truncated"] > 0, ended


def test_terminated_and_truncated_follow_the_env_info(flat_env):
    """is_terminated / is_truncated of the stepped state (before the reset) equal info's;
    final_observation is the observation of that state."""
    env, params = flat_env
    _, state = env.reset(jax.random.PRNGKey(0), params)
    step_env = jax.jit(lambda s, a: env.step_env(None, s, a, params))
    for action in [0, 1, 2] * 10:            # no Done: the 30th action truncates
        st = step_env(state, jnp.int32(action))[1]
        assert bool(env.is_truncated(st, params)) == bool(st.steps >= 30)
        assert not bool(env.is_terminated(st, params))
        obs, state, _, term, trunc, info = env.step(jax.random.PRNGKey(1), state,
                                                    jnp.int32(action), params)
        np.testing.assert_array_equal(info["final_observation"], env.get_obs(st, params))
    assert bool(trunc) and not bool(term) and int(state.steps) == 0   # reset after it
    _, st, _, term, info = step_env(state, jnp.int32(nav.DONE))
    assert bool(term) and bool(env.is_terminated(st, params)) and not bool(info["truncated"])
    assert {"success", "optimal_len", "path_len"} <= set(info)


def test_dict_observation_holds_the_same_parts(flat_env, train_rooms):
    env, params = flat_env
    denv = gymnax_env.NavEnv("dict", max_steps=30, default_params=params)
    key = jax.random.PRNGKey(5)
    flat, state = env.reset(key, params)
    parts, state2 = denv.reset(key, params)
    assert same(state, state2)
    space = denv.observation_space(params)
    assert set(parts) == set(gymnax_env.OBS_PARTS) == set(space.spaces)   # jit sorts keys
    for name, x in gymnax_env.unflatten(flat, train_rooms).items():
        np.testing.assert_array_equal(parts[name], x, err_msg=name)
        assert parts[name].shape == space.spaces[name].shape
    assert flat.shape == env.observation_space(params).shape
    assert bool(env.observation_space(params).contains(flat))


def test_one_compiled_step_serves_other_rewards_caps_and_scene_sets(flat_env, train_rooms):
    """Rewards, caps and the scenes are traced: new values (and another set of the same
    shapes, whatever its info) reuse the compiled step."""
    env, params = flat_env
    key = jax.random.PRNGKey(0)
    _, state = env.reset(key, params)
    env.step(key, state, 5, params)
    before = gymnax_env.NavEnv._step._cache_size()
    other = gymnax_env.make_params(
        train_rooms.replace(info=(("preset", "other"),), det_conf=train_rooms.det_conf * 0),
        nav.EnvParams(success_reward=9.0, step_penalty=-0.5, step_caps=(5, 10, 20, 30)))
    _, _, reward, *_ = env.step(key, state, 0, other)
    assert float(reward) == -0.5
    assert gymnax_env.NavEnv._step._cache_size() == before
    with pytest.raises(ValueError, match="max_steps"):
        gymnax_env.NavEnv("flat", max_steps=20, default_params=params.replace(
            step_caps=jnp.array([30, 30, 30, 30])))
    with pytest.raises(ValueError, match="obs must be one of"):
        gymnax_env.NavEnv("pixels")


def test_make_returns_env_and_params(tiny_scenes):
    env, params = gymnax_env.make(scenes=tiny_scenes, split="val", obs="dict",
                                  rules=nav.EnvParams.evaluation())
    assert env.max_steps == 200 == params.max_steps_in_episode
    assert params.scenes.num_scenes == 4 and env.default_params is params
    assert env.num_actions == 6 and env.action_space(params).n == 6


def test_log_and_flatten_wrappers_under_jit_vmap_and_the_five_value_api(flat_env):
    env, params = flat_env
    wrapped = wrappers.LogWrapper(wrappers.FlattenObservationWrapper(env))
    B, T = 4, 40
    reset = jax.jit(jax.vmap(wrapped.reset, (0, None)))
    step = jax.jit(jax.vmap(wrapped.step, (0, 0, 0, None)))
    obs, state = reset(jax.random.split(jax.random.PRNGKey(0), B), params)
    assert obs.shape == (B,) + env.observation_space(params).shape

    def body(c, key):
        state, n = c
        k_act, k_env = jax.random.split(key)
        action = jax.random.randint(k_act, (B,), 0, 6)
        obs, state, reward, term, trunc, info = step(jax.random.split(k_env, B), state,
                                                     action, params)
        return (state, n + info["returned_episode"].sum()), reward

    (state, episodes), rewards = jax.jit(lambda s, ks: jax.lax.scan(body, (s, 0), ks))(
        state, jax.random.split(jax.random.PRNGKey(1), T))
    assert rewards.shape == (T, B) and int(episodes) > 0
    assert bool(state.returned_episode_valid.any())

    legacy = wrappers.LegacyStepAPIWrapper(env)
    _, s = legacy.reset(jax.random.PRNGKey(0), params)
    out = legacy.step(jax.random.PRNGKey(1), s, nav.DONE, params)
    assert len(out) == 5 and bool(out[3])           # obs, state, reward, done, info
    assert bool(out[4]["terminated"]) and not bool(out[4]["truncated"])

    dm = wrappers.GymnaxToDmEnvWrapper(env)
    ts = dm.step(jax.random.PRNGKey(1), dm.reset(jax.random.PRNGKey(0), params), nav.DONE,
                 params)
    assert float(ts.discount) == 0.0


@pytest.mark.parametrize("obs", ["flat", "dict"])
def test_gymnasium_env_checker_passes(flat_env, obs):
    """gymnax_env.GymEnv (gymnax's GymnaxToGymWrapper, numpy out, seeded np_random, the
    two things gymnax 1.0.1's wrapper lacks for the checker) passes check_env."""
    from gymnasium.utils.env_checker import check_env
    _, params = flat_env
    env = gymnax_env.GymEnv(gymnax_env.NavEnv(obs, 30, params), params, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")     # no warning but two known ones:
        warnings.filterwarnings("ignore", message=".*return_info.*")  # gymnax's signature
        warnings.filterwarnings("ignore", message=".*infinity.*")  # features are unbounded
        check_env(env, skip_render_check=True)
    for bad in (9, -1, 2.5, True):        # refused, not aliased (9 would act as Done)
        with pytest.raises(ValueError, match=r"action .* invalid: expected integers in 0\.\.5"):
            env.step(bad)


def test_bad_actions_states_and_params(flat_env, train_rooms):
    """Issue 38. Under jit an invalid action (7, -1, 2.7, nan) or a state outside the
    params' scenes is a no-op flagged in info (state unchanged, reward 0, not done), never
    an alias of a real action (7 acted as Done, -1 as MoveAhead, 2.7 as 2); eager calls
    and the Python entry points raise one clear ValueError."""
    env, params = flat_env
    keys = jax.random.split(jax.random.PRNGKey(5), 8)
    _, state = jax.vmap(env.reset, (0, None))(keys, params)
    # rows 0-3 invalid actions, 4-6 valid (2.0 is action 2), row 7 a state of other scenes
    action = jnp.array([7, -1, 2.7, jnp.nan, 2.0, 5, 0, 0], jnp.float32)
    foreign = state.replace(scene=state.scene.at[7].set(99),
                            state=state.state.at[7].set(train_rooms.num_states + 5))
    _, new, reward, term, trunc, info = jax.jit(jax.vmap(env.step, (0, 0, 0, None)))(
        keys, foreign, action, params)
    bad = np.array([1, 1, 1, 1, 0, 0, 0, 1], bool)
    np.testing.assert_array_equal(info["invalid_action"], [1, 1, 1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(info["invalid_state"], [0, 0, 0, 0, 0, 0, 0, 1])
    for a, b in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(foreign)):
        np.testing.assert_array_equal(np.asarray(a)[bad], np.asarray(b)[bad])
    assert not np.asarray(reward)[bad].any() and not np.asarray(term | trunc)[bad].any()
    # the valid rows acted: 2.0 as RotateRight, 5 as Done (the episode ended), 0
    assert np.asarray(new.prev_action)[[4, 6]].tolist() == [2, 0] and bool(term[5])
    assert not np.asarray(info["success"] | info["failed"] | info["revisited"])[bad].any()
    # eager calls: one line each, before anything is compiled
    one = jax.tree_util.tree_map(lambda x: x[0], state)
    for a in (7, -1, 2.7):
        with pytest.raises(ValueError, match=rf"action {a} invalid: expected integers in 0..5"):
            env.step(keys[0], one, a, params)
    with pytest.raises(ValueError, match="is not a state of these scenes"):
        env.step(keys[0], jax.tree_util.tree_map(lambda x: x[7], foreign), 0, params)
    with pytest.raises(ValueError, match="is not a state of these scenes"):
        nav.step_env(jax.tree_util.tree_map(lambda x: x[7], foreign), 0, train_rooms,
                     nav.EnvParams())
    # params built on the host: one cap per room type, caps >= 1, finite rewards
    with pytest.raises(ValueError, match=r"'step_caps': expected 4 caps, one per room type"):
        nav.EnvParams(step_caps=(30, 30, 30))
    with pytest.raises(ValueError, match=r"'step_caps': expected integers >= 1"):
        nav.EnvParams(step_caps=(30, 30, 0, 30))
    with pytest.raises(ValueError, match=r"'step_caps': expected shape \(4,\)"):
        env.step(keys[0], one, 0, params.replace(step_caps=jnp.array([30, 30, 30])))
    with pytest.raises(ValueError, match=r"'success_reward': expected a finite number"):
        gymnax_env.make_params(train_rooms, nav.EnvParams(success_reward=float("nan")))
    with pytest.raises(ValueError, match=r"split must be one of"):
        gymnax_env.make(split="tset")
    with pytest.raises(ValueError, match=r"obs must be one of"):
        gymnax_env.make(obs="pixels")


def test_vector_gym_wrapper_steps_16_envs_with_numpy_actions(flat_env):
    from gymnax.wrappers import GymnaxToVectorGymWrapper
    env, params = flat_env
    venv = GymnaxToVectorGymWrapper(env, num_envs=16, params=params, seed=0)
    obs, _ = venv.reset(seed=1)
    assert obs.shape == (16,) + env.observation_space(params).shape
    assert venv.single_action_space.n == 6 and venv.observation_space.shape == obs.shape
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(35):
        obs, reward, term, trunc, info = venv.step(rng.integers(0, 6, 16))
        assert np.asarray(obs).shape[0] == np.asarray(reward).shape[0] == 16
        ends += int(np.asarray(term | trunc).sum())
    assert ends >= 16      # every env ended an episode within its cap of 30


def _ppo():
    spec = importlib.util.spec_from_file_location("ppo_gymnax", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod        # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def test_ppo_example_bad_options_are_one_line_before_training(cli_error, capsys):
    """Issue 38: examples/ppo_gymnax.py follows the CLIs' convention (run_cli): no
    `success nan` for --eval-episodes 0, no traceback for --num-envs 0 or --scenes smal."""
    ppo = _ppo()
    for argv, message in ((["--eval-episodes", "0"], "--eval-episodes: expected an integer "
                                                     ">= 1, got 0"),
                          (["--num-envs", "0"], "--num-envs: expected an integer >= 1, got 0"),
                          (["--num-envs", "6"], "num_envs 6 is not a multiple of "
                                                "num_minibatches 4"),
                          (["--scenes", "smal"], "unknown scene preset 'smal'")):
        assert message in cli_error(ppo.main, argv)
    assert "update" not in capsys.readouterr().out            # nothing trained
    with pytest.raises(ValueError, match="num_envs .episodes.: expected an integer >= 1"):
        ppo.evaluate(None, ppo.Config(), num_envs=0, policy="random")


@pytest.mark.slow
def test_ppo_example_beats_random_on_val_rooms(tiny_scenes):
    """examples/ppo_gymnax.py: PPO-GRU trained on the 8 tiny train rooms (fixed seed)
    succeeds clearly more often than a random policy on the 4 unseen val rooms. Half the
    example's 150 k env steps: val success 0.135 at 75 k, 0.145 at 150 k, random 0.025
    (20 s against 30 s alone; docs/history/test-suite-time.md)."""
    import dataclasses
    ppo = _ppo()
    config = dataclasses.replace(ppo.Config(), total_timesteps=75_000)
    env, params = gymnax_env.make(scenes=tiny_scenes, split="train")
    trained_params, metrics = ppo.train(config, env, params)
    assert np.isfinite(metrics["value_loss"]).all()
    val_env, val_params = gymnax_env.make(scenes=tiny_scenes, split="val")
    kw = dict(num_envs=512, seed=1)
    trained = ppo.evaluate(trained_params, config, val_env, val_params, **kw)["success"]
    rand = ppo.evaluate(None, config, val_env, val_params, policy="random", **kw)["success"]
    assert trained >= 3 * rand and trained >= rand + 0.05, (trained, rand)
