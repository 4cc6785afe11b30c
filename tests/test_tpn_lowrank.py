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
from orgnav_jax.tpn.lowrank import SLOT_BLOCK, make_plan, plan_floats
from orgnav_jax.tpn.test_time import (_tpn_policy, build_tpn, default_batch_size,
                                   fast_weights, init_tpn_params, tpn_policy)
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


@jax.jit
def _first_obs(key, test):
    _, state = jax.vmap(env.reset, in_axes=(0, None, None))(
        jax.random.split(key, B), test, env.EnvParams.evaluation())
    return jax.vmap(env.observe, in_axes=(0, None))(state, test)


def observations(test, steps: int, deadlock=None):
    """`steps` batches of B observations of random states (a new one every step);
    deadlock (B,) overrides the env's flag."""
    out = []
    for t in range(steps):
        obs = _first_obs(jax.random.PRNGKey(100 + t), test)
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
    """Consecutive updates of all parameters, every step (different observations and
    targets), over more than one block of slots, then a reset: the same weights, LSTM
    state and policy as the dense reference (full copies)."""
    model, params, tpn, tpn_params = setup(name)
    R = SLOT_BLOCK + 2                  # updates 0..R-1 fill two blocks; reset at step R
    cfg = get_tpn_config(scope="all", when="all", target="random", tpn_lr=0.05,
                         reset_every=R, placement="state").test_time()
    assert make_plan(params, "all", R).sites, "the LSTM should be low-rank here"
    pparams = {"base": params, "tpn": tpn_params}
    obs = observations(test_split, R + 2)
    fresh = [[True] * B] + [[False] * B] * (R + 1)
    runs = {impl: drive(tpn_policy(model, tpn, cfg, "x", 0.0, impl), pparams, test_split, obs,
                        fresh) for impl in ("dense", "lowrank")}
    base = traverse_util.flatten_dict(params)
    for t in (1, R - 1, R, R + 1):      # 2 and R updates, then 1 and 2 after the reset
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
    assert [int(c) for c in low[R - 1].fast.count] == [R - 1] * B
    assert [int(c) for c in low[R].fast.count] == [0] * B     # reset at step R
    assert bool(low[R].fast.newest_on.all())


@pytest.mark.parametrize("scope", ["actor", "all"])
def test_updates_never_leak_across_environments_or_episodes(setup, test_split, scope):
    model, params, tpn, tpn_params = setup("baseline")
    cfg = get_tpn_config(scope=scope, tpn_lr=0.5, placement="state").test_time()
    policy = tpn_policy(model, tpn, cfg)
    pparams = {"base": params, "tpn": tpn_params}
    # env 0 is in deadlock at every step, envs 1 and 2 never are
    obs = observations(test_split, 4, deadlock=[True, False, False])
    T, F = True, False
    carries = drive(policy, pparams, test_split, obs, [[T, T, T], [F, F, F], [F, F, F],
                                                      [T, F, F]])
    w = [weights(model, cfg, params, "auto", c) for c in carries]
    trained = {k: np.asarray(v) for k, v in traverse_util.flatten_dict(params).items()}
    same = lambda a, b: all(np.array_equal(a[k], b[k]) for k in a)
    row = lambda ws, i: {k: v[i] for k, v in ws.items()}
    # env 0 updated; the others act with the trained weights (no leak across environments)
    assert not same(row(w[2], 0), trained)
    assert same(row(w[2], 1), trained) and same(row(w[2], 2), trained)
    assert [int(u) for u in carries[2].updates] == [3, 0, 0]
    # a new episode in env 0 starts from the trained weights (no leak across episodes):
    # after its first step it holds exactly one update from them, as in a first episode
    first = weights(model, cfg, params, "auto", drive(policy, pparams, test_split, obs[3:],
                                                      [[T, T, T]])[0])
    for k in w[3]:
        np.testing.assert_allclose(w[3][k][0], first[k][0], rtol=1e-6, atol=1e-7)
    assert int(carries[3].updates[0]) == 1
    # envs 1 and 2 are still untouched
    assert same(row(w[3], 1), trained) and same(row(w[3], 2), trained)


def step_probs(model, params, inputs, lstm):
    return np.asarray(jax.nn.softmax(model.apply(params, inputs, lstm)[0]))


def test_reset_every_restores_the_trained_weights(setup, test_split):
    """Deadlocks at steps 0-2, none at step 3: with reset_every=3 the policy at step 3
    is the trained model's (same LSTM state); without resets it is not."""
    model, params, tpn, tpn_params = setup("baseline")
    pparams = {"base": params, "tpn": tpn_params}
    obs = [o.replace(deadlock=jnp.full(B, t < 3))
           for t, o in enumerate(observations(test_split, 4))]
    fresh = [[True] * B] + [[False] * B] * 3
    inputs3 = model_inputs(test_split, obs[3])
    for reset_every, equal in ((3, True), (0, False)):
        cfg = get_tpn_config(scope="all", tpn_lr=0.5, reset_every=reset_every,
                             placement="state").test_time()
        carries = drive(tpn_policy(model, tpn, cfg), pparams, test_split, obs, fresh)
        trained = step_probs(model, params, inputs3, carries[2].lstm)
        acted = np.asarray(carries[3].memory.prev_probs)       # softmax of step 3's logits
        assert np.allclose(acted, trained, rtol=1e-5, atol=1e-6) == equal, reset_every
        assert [int(u) for u in carries[3].updates] == [3] * B
        assert [int(s) for s in carries[3].steps] == [3] * B


def test_train_mode_is_dropout_during_the_tpn_evaluation(setup, test_split):
    """--tpn-train-mode: with dropout 0 nothing changes; with dropout > 0 the policy
    differs (a fresh mask each step); without the flag the dropout rate is unused."""
    model, params, tpn, tpn_params = setup("baseline")
    pparams = {"base": params, "tpn": tpn_params}
    obs = observations(test_split, 3, deadlock=[True, False, True])
    fresh = [[True] * B] + [[False] * B] * 2

    def probs(dropout, train_mode, make=tpn_policy):
        cfg = get_tpn_config(scope="all", tpn_lr=0.1, tpn_train_mode=train_mode).test_time()
        carries = drive(make(model, tpn, cfg, "x", dropout, "auto"), pparams, test_split,
                        obs, fresh)
        return np.stack([np.asarray(c.memory.prev_probs) for c in carries])

    off = probs(0.0, False)
    # the programs themselves (not the shared policy): train mode at a rate of 0, and a
    # rate without train mode, equal the plain policy; what lets tpn_policy hand it out
    np.testing.assert_array_equal(probs(0.0, True, make=_tpn_policy), off)
    np.testing.assert_array_equal(probs(0.5, False, make=_tpn_policy), off)
    # without dropout applied those are one policy, so one compiled step
    plain = get_tpn_config(scope="all", tpn_lr=0.1).test_time()
    train = get_tpn_config(scope="all", tpn_lr=0.1, tpn_train_mode=True).test_time()
    assert tpn_policy(model, tpn, train, "x", 0.0) is tpn_policy(model, tpn, plain, "x", 0.5) \
        is tpn_policy(model, tpn, plain, "x", 0.0)
    assert tpn_policy(model, tpn, train, "x", 0.5) is not tpn_policy(model, tpn, plain, "x")
    on = probs(0.5, True)
    assert np.abs(on - off).max() > 1e-3
    np.testing.assert_array_equal(probs(0.5, True), on)          # deterministic per key


def test_the_evaluation_compiles_once(setup, test_split):
    """Three batches of episodes, one trace of the policy step (and so one compile)."""
    model, params, tpn, tpn_params = setup("org")
    base = tpn_policy(model, tpn, get_tpn_config(scope="all", tpn_lr=1e-2).test_time())
    traces = []

    def act(*args):
        traces.append(1)
        return base.act(*args)

    policy = evaluation.Policy("counted", base.init, act)
    episodes = sample_episodes(test_split, 3, seed=0, split="test")
    out = evaluation.run_episodes(policy, {"base": params, "tpn": tpn_params}, test_split,
                                  episodes, env.EnvParams.evaluation(), batch_size=4)
    assert len(out["success"]) == len(episodes) == 12 and len(traces) == 1


def test_cli_options_and_batch_size(setup):
    args = evaluate.parser().parse_args(["--tpn", "x", "--tpn-train-mode", "true",
                                         "--reset-every", "0", "--scope", "all"])
    assert tpn_overrides_from_args(args) == {"tpn_train_mode": True, "reset_every": 0,
                                             "scope": "all"}
    with pytest.raises(SystemExit):
        evaluate.parser().parse_args(["--tpn", "x", "--tpn-train-mode", "maybe"])
    with pytest.raises(ValueError, match="reset_every"):
        get_tpn_config(reset_every=-1)
    _, params, _, _ = setup("baseline")
    # low-rank state: far smaller than a copy of the LSTM, so far larger batches
    dense, slots = plan_floats(params, make_plan(params, "all", 50))
    assert dense + slots < sum(int(v.size) for v in jax.tree_util.tree_leaves(params))
    assert default_batch_size(params, get_tpn_config(scope="all")) > default_batch_size(
        params, "all", impl="dense")


def test_release_placement_corrects_step_t_and_acts_from_step_t_plus_1(setup, test_split):
    """placement "release" (issue 41): step 0's logits are the trained model's and are not
    re-run; at step 1, the rows whose state is flagged (envs 0 and 2) act with the weights
    after one SGD step of CE(step 0's logits, step 0's target), computed by hand here; env 1
    acts with the trained weights; at step 2 (no flag) step 1's pending update is dropped.
    The low-rank weights equal the dense reference's."""
    model, params, tpn, tpn_params = setup("baseline")
    lr = 0.5
    cfg = get_tpn_config(scope="all", when="deadlock", target="random", tpn_lr=lr,
                         placement="release").test_time()
    pparams = {"base": params, "tpn": tpn_params}
    flags = [[False] * B, [True, False, True], [False] * B]
    obs = [o.replace(deadlock=jnp.asarray(f))
           for o, f in zip(observations(test_split, 3), flags)]
    fresh = [[True] * B, [False] * B, [False] * B]
    runs = {impl: drive(tpn_policy(model, tpn, cfg, "x", 0.0, impl), pparams, test_split,
                        obs, fresh) for impl in ("dense", "lowrank")}
    # by hand: the trained model's step 0, its target (the policy's random target of step
    # 0, drawn from the key drive gives it), one SGD step per row, then step 1
    inputs = [model_inputs(test_split, o) for o in obs]
    carry0 = model.initial_carry(B)
    logits0, _, carry1, _ = model.apply(params, inputs[0], carry0)
    target0 = jax.random.randint(jax.random.PRNGKey(0), (B,), 0, 6)
    row = lambda tree, i: jax.tree_util.tree_map(lambda x: x[i:i + 1], tree)

    def ce(p, i):
        logits = model.apply(p, row(inputs[0], i), row(carry0, i))[0]
        return -jax.nn.log_softmax(logits)[0, target0[i]]

    probs1 = []
    for i in range(B):
        p = params
        if flags[1][i]:
            g = jax.jit(jax.grad(ce), static_argnums=1)(params, i)
            p = jax.tree_util.tree_map(lambda w, d: w - lr * d, params, g)
        probs1.append(jax.nn.softmax(model.apply(p, row(inputs[1], i), row(carry1, i))[0])[0])
    for impl, carries in runs.items():
        np.testing.assert_allclose(np.asarray(carries[0].memory.prev_probs),
                                   np.asarray(jax.nn.softmax(logits0)), rtol=1e-5, atol=1e-6,
                                   err_msg=impl)           # step 0: not re-run, not updated
        np.testing.assert_allclose(np.asarray(carries[1].memory.prev_probs),
                                   np.stack(probs1), rtol=1e-4, atol=1e-5, err_msg=impl)
        assert [int(u) for u in carries[1].updates] == [1, 0, 1], impl
        assert [int(u) for u in carries[2].updates] == [1, 0, 1], impl
        w1, w2 = (weights(model, cfg, params, impl, c) for c in carries[1:])
        for k in w1:                    # step 1's update is pending, never applied at step 2
            np.testing.assert_array_equal(w2[k], w1[k], err_msg=str(k))
    dense, low = (weights(model, cfg, params, impl, runs[impl][1]) for impl in runs)
    for k in dense:
        np.testing.assert_allclose(low[k], dense[k], rtol=1e-4, atol=2e-6, err_msg=str(k))
    # the state placement at step 1 differs (it updates on step 1's own logits and re-runs;
    # test_reset_every's program, so no new compile)
    state = drive(tpn_policy(model, tpn, get_tpn_config(scope="all", tpn_lr=0.5,
                                                        reset_every=0).test_time()),
                  pparams, test_split, obs, fresh)
    assert not np.allclose(np.asarray(state[1].memory.prev_probs)[0], np.asarray(probs1[0]),
                           atol=1e-5)
