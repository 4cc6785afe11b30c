"""TPN's test-time update on all parameters: low-rank fast weights equal dense ones, never
leak across episodes or environments, reset every N steps; train mode; one compile."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from orgnav_jax import env, evaluate, evaluation
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.models import build_model, init_params, model_inputs
from orgnav_jax.tpn.config import get_tpn_config, tpn_overrides_from_args
from orgnav_jax.tpn.lowrank import make_plan, plan_floats
from orgnav_jax.tpn.policy import (build_tpn, default_batch_size, fast_weights,
                                   init_tpn_params, tpn_policy)
from orgnav_jax.training.config import get_config

B = 3


@pytest.fixture(scope="module")
def setup(tiny_scenes):
    """name -> (model, params, TPN, TPN params): a freshly initialised navigation model of
    the tiny preset and its TPN."""
    @functools.cache
    def make(name: str):
        cfg = get_config("tiny", model=name)
        train = tiny_scenes.split_view("train")
        model = build_model(cfg, train)
        params = init_params(model, jax.random.PRNGKey(0), train)
        tpn = build_tpn(cfg, get_tpn_config())
        return model, params, tpn, init_tpn_params(tpn, cfg, jax.random.PRNGKey(1))
    return make


@pytest.fixture(scope="module")
def test_split(tiny_scenes):
    return tiny_scenes.split_view("test").to_device()


def observations(test, steps: int, deadlock=None):
    """`steps` batches of B observations of random states (a new one every step);
    deadlock (B,) overrides the env's flag."""
    out = []
    for t in range(steps):
        _, state = jax.vmap(env.reset, in_axes=(0, None, None))(
            jax.random.split(jax.random.PRNGKey(100 + t), B), test, env.EnvParams.evaluation())
        obs = jax.vmap(env.observe, in_axes=(0, None))(state, test)
        out.append(obs if deadlock is None else obs.replace(deadlock=jnp.asarray(deadlock)))
    return out


def drive(policy, pparams, test, obs_steps, fresh_steps):
    """policy.act on the given observations -> the carry after every step."""
    act = jax.jit(policy.act)
    carry, carries = policy.init(B, pparams), []
    for t, (obs, fresh) in enumerate(zip(obs_steps, fresh_steps)):
        _, carry = act(pparams, carry, obs, jax.random.PRNGKey(t), test, jnp.asarray(fresh))
        carries.append(carry)
    return carries


def weights(model, cfg, params, impl, carry):
    """{path: (B, ...)} each environment's current fast weights of cfg.scope."""
    fw = fast_weights(model, cfg, params, impl)
    return {k: np.asarray(v) for k, v in fw.materialize(params, carry.fast).items()}


@pytest.mark.parametrize("name", ["baseline", "org"])
def test_lowrank_fast_weights_equal_dense_copies(setup, test_split, name):
    """Five consecutive updates of all parameters, every step (different observations
    and targets), with a reset after three: the same weights, LSTM state and policy as
    the dense reference (full copies)."""
    model, params, tpn, tpn_params = setup(name)
    cfg = get_tpn_config(scope="all", when="all", target="random", tpn_lr=0.05,
                         reset_every=3).test_time()
    assert make_plan(params, "all", 3).sites, "the LSTM should be low-rank here"
    pparams = {"base": params, "tpn": tpn_params}
    obs = observations(test_split, 5)
    fresh = [[True] * B] + [[False] * B] * 4
    runs = {impl: drive(tpn_policy(model, tpn, cfg, "x", 0.0, impl), pparams, test_split, obs,
                        fresh) for impl in ("dense", "lowrank")}
    base = traverse_util.flatten_dict(params)
    for t in (1, 2, 3, 4):              # 2 and 3 updates, then 1 and 2 after the reset
        dense = weights(model, cfg, params, "dense", runs["dense"][t])
        low = weights(model, cfg, params, "lowrank", runs["lowrank"][t])
        assert sorted(dense) == sorted(low)
        for k in dense:
            np.testing.assert_allclose(low[k], dense[k], rtol=1e-4, atol=2e-6, err_msg=str(k))
        moved = sum(np.abs(dense[k] - np.asarray(base[k])[None]).max() > 1e-6 for k in dense)
        assert moved >= 10, f"only {moved} parameter arrays changed"
        for a, b in zip(jax.tree_util.tree_leaves((runs["dense"][t].lstm,
                                                   runs["dense"][t].memory.prev_probs)),
                        jax.tree_util.tree_leaves((runs["lowrank"][t].lstm,
                                                   runs["lowrank"][t].memory.prev_probs))):
            np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-4, atol=2e-6)
    low = runs["lowrank"]
    assert [int(c) for c in low[2].fast.count] == [2] * B     # + the newest, not yet written
    assert [int(c) for c in low[3].fast.count] == [0] * B     # reset at step 3
    assert bool(low[3].fast.newest_on.all())
