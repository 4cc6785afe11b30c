"""TPN stage 2 and the test-time update: fast weights, gradients, CLI, resume, errors."""

from __future__ import annotations

import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import env, evaluate, evaluation
from orgnav_jax import scenes as scenes_mod
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.models import model_inputs
from orgnav_jax.tpn.config import TPN_LR, get_tpn_config, load_tpn_config
from orgnav_jax.tpn.fast_weights import policy_ce, sgd_step, split_scope, split_step
from orgnav_jax.tpn.test_time import build_tpn, init_tpn_params, load_tpn_policy
from orgnav_jax.tpn.stage2 import collect, train_tpn, tpn_loss
from orgnav_jax.training.config import get_config
from orgnav_jax.training.loop import train
from orgnav_jax.training.runs import load_run_model, model_policy


@pytest.fixture(scope="module")
def base_run(tmp_path_factory, tiny_scenes):
    """A briefly trained navigation run on the tiny scenes (untrained-ish weights suffice)."""
    root = tmp_path_factory.mktemp("tpn")
    scenes_mod.save(tiny_scenes, root / "scenes")
    cfg = get_config("tiny", scenes_dir=str(root / "scenes"), num_envs=16, rollout_len=8,
                     updates_per_chunk=2, total_env_steps=16 * 8 * 2 * 2, eval_every_chunks=1,
                     eval_episodes_per_room_type=2, checkpoint_every_chunks=1,
                     run_dir=str(root / "base"))
    train(cfg, progress=False)
    return str(root / "base")


def tpn_cfg(base_run, run_dir, **kw):
    # placement state, optim ours: the mechanics these tests pin (the release's placement
    # and optimiser, the defaults, have their own tests below and in test_tpn_lowrank.py)
    fields = dict(base_dir=base_run, num_envs=8, episode_cap=16, total_episodes=8 * 2 * 3,
                  placement="state", optim="ours",
                  updates_per_chunk=2, eval_every_chunks=1, eval_episodes_per_room_type=2,
                  checkpoint_every_chunks=1, run_dir=str(run_dir))
    return get_tpn_config(**{**fields, **kw})


@pytest.fixture(scope="module")
def tpn_run(base_run, tmp_path_factory):
    cfg = tpn_cfg(base_run, tmp_path_factory.mktemp("tpnrun") / "tpn")
    train_tpn(cfg, progress=False)
    return cfg.run_dir


@pytest.fixture(scope="module")
def loaded(base_run):
    model, params, cfg = load_run_model(base_run)
    from orgnav_jax.training.runs import scenes_for
    test = scenes_for(cfg).split_view("test").to_device()
    return model, params, cfg, test


def first_obs(test, num, key=0):
    params = env.EnvParams.evaluation()
    _, state = jax.vmap(env.reset, in_axes=(0, None, None))(
        jax.random.split(jax.random.PRNGKey(key), num), test, params)
    return jax.vmap(env.observe, in_axes=(0, None))(state, test)


def test_one_sgd_step_lowers_the_cross_entropy_of_the_target(loaded):
    model, params, _, test = loaded
    obs = first_obs(test, 4)
    inputs = model_inputs(test, obs)
    carry = model.initial_carry(4)
    for scope in ("actor", "trunk", "all"):
        scoped, rest = split_scope(params, scope)
        shared, per_env = split_step(model, scope)
        per_env_jit = jax.jit(per_env)
        features = jax.tree_util.tree_map(lambda x: x[0],
                                          jax.jit(shared)(params, inputs, carry))
        logits, _, _ = per_env_jit(scoped, rest, features)
        target = jnp.argmin(logits)                    # the least likely action
        stepped = jax.jit(lambda s, r, f, t: sgd_step(per_env, s, r, f, t, 1e-2))(
            scoped, rest, features, target)
        after, _, _ = per_env_jit(stepped, rest, features)
        assert float(policy_ce(after, target)) < float(policy_ce(logits, target)) - 1e-4, scope
        # with unchanged weights, one environment's step equals the batched model's
        full_logits = model.apply(params, inputs, carry)[0][0]
        np.testing.assert_allclose(np.asarray(logits), np.asarray(full_logits), atol=1e-5)


def test_with_zero_lr_the_tpn_policy_acts_as_the_base_model(loaded, tpn_run):
    """Fast weights that never move reproduce the trained model's greedy episodes."""
    model, params, _, test = loaded
    policy, pparams, _, cfg = load_tpn_policy(tpn_run, tpn_lr=0.0, when="all")
    episodes = sample_episodes(test, 6, seed=1, split="test")
    ev = env.EnvParams.evaluation()
    with_tpn = evaluation.run_episodes(policy, pparams, test, episodes, ev, batch_size=24)
    base = evaluation.run_episodes(model_policy(model), params, test, episodes, ev,
                                   batch_size=24)
    for k in ("success", "path_len", "steps"):
        np.testing.assert_array_equal(with_tpn[k], base[k])


def run_policy_steps(policy, pparams, test, obs, fresh_pattern):
    """Drive policy.act (jitted, as evaluation runs it) on fixed observations;
    fresh_pattern[t] (B,) bool."""
    carry = policy.init(obs.state.shape[0], pparams)
    act = jax.jit(policy.act)
    carries = []
    for t, fresh in enumerate(fresh_pattern):
        _, carry = act(pparams, carry, obs, jax.random.PRNGKey(t), test, jnp.asarray(fresh))
        carries.append(carry)
    return carries


def test_fast_weights_belong_to_one_episode_of_one_environment(loaded, tpn_run):
    model, params, _, test = loaded
    policy, pparams, _, cfg = load_tpn_policy(tpn_run, tpn_lr=0.5, when="deadlock",
                                              scope="actor")
    obs = first_obs(test, 3)
    # env 0 is in deadlock at every step, envs 1 and 2 never are
    obs = obs.replace(deadlock=jnp.array([True, False, False]))
    base_actor, _ = split_scope(pparams["base"], "actor")
    T, F = True, False
    carries = run_policy_steps(policy, pparams, test, obs,
                               [[T, T, T], [F, F, F], [F, F, F], [T, F, F]])
    fast = lambda c, b: jax.tree_util.tree_map(lambda x: np.asarray(x[b]), c.fast)
    same = lambda a, b: all(np.array_equal(x, y) for x, y in zip(
        jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    base_np = jax.tree_util.tree_map(np.asarray, base_actor)
    # env 0 updated; the others kept the trained weights (no leak across environments)
    assert not same(fast(carries[2], 0), base_np)
    assert same(fast(carries[2], 1), base_np) and same(fast(carries[2], 2), base_np)
    assert [int(u) for u in carries[2].updates] == [3, 0, 0]
    # a new episode in env 0 starts from the trained weights (no leak across episodes):
    # after its first step it holds exactly one update from them
    one_step = run_policy_steps(policy, pparams, test, obs, [[T, T, T]])[0]
    assert same(fast(carries[3], 0), fast(one_step, 0))
    assert int(carries[3].updates[0]) == 1
    # a batch of one gives env 0 the same weights as the batch of three
    solo = jax.tree_util.tree_map(lambda x: x[:1], obs)
    solo_carry = run_policy_steps(policy, pparams, test, solo, [[T], [F], [F]])[2]
    for a, b in zip(jax.tree_util.tree_leaves(fast(carries[2], 0)),
                    jax.tree_util.tree_leaves(fast(solo_carry, 0))):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_stage2_gradients_reach_the_tpn_parameters_only(loaded, base_run, tmp_path):
    model, params, nav_cfg, test = loaded
    cfg = tpn_cfg(base_run, tmp_path / "t", episode_cap=12)
    tpn = build_tpn(nav_cfg, cfg)
    tpn_params = init_tpn_params(tpn, nav_cfg, jax.random.PRNGKey(0))

    def objective(base_params, tpn_params, test):
        batch = collect(model, base_params, cfg, test, jax.random.PRNGKey(1), 16)
        batch = batch.replace(deadlock=jnp.ones_like(batch.deadlock))  # every step counts
        return tpn_loss(tpn_params, tpn, batch)[0]

    g_base, g_tpn = jax.jit(jax.grad(objective, argnums=(0, 1)))(params, tpn_params, test)
    assert all(float(jnp.abs(g).max()) == 0.0 for g in jax.tree_util.tree_leaves(g_base))
    norms = [float(jnp.abs(g).max()) for g in jax.tree_util.tree_leaves(g_tpn)]
    assert all(np.isfinite(norms)) and sum(n > 0 for n in norms) >= len(norms) - 2


def test_collect_marks_whole_episodes(loaded, base_run, tmp_path):
    model, params, nav_cfg, test = loaded
    cfg = tpn_cfg(base_run, tmp_path / "t", episode_cap=20)
    b = collect(model, params, cfg, test, jax.random.PRNGKey(2), 12)
    valid = np.asarray(b.valid)
    assert valid[:, 0].all()
    # once an episode ends it stays ended
    assert (np.diff(valid.astype(int), axis=1) <= 0).all()
    assert b.h.shape == (12, 20, nav_cfg.hidden) and b.probs.shape == (12, 20, 6)
    np.testing.assert_allclose(np.asarray(b.probs).sum(-1), 1.0, rtol=1e-5)


def test_stage2_kill_and_resume_equals_an_uninterrupted_run(base_run, tmp_path):
    full = train_tpn(tpn_cfg(base_run, tmp_path / "full"), progress=False)
    cfg = tpn_cfg(base_run, tmp_path / "resumed")
    train_tpn(cfg, progress=False, stop_after_chunks=1)
    resumed = train_tpn(cfg, resume=True, progress=False)
    for a, b in zip(jax.tree_util.tree_leaves(full["runner"].params),
                    jax.tree_util.tree_leaves(resumed["runner"].params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert full["best_val"] == resumed["best_val"]


def test_stage2_programs_are_shared_by_runs_of_one_computation(loaded, base_run, tmp_path):
    """Runs that differ only in bookkeeping or test-time fields get the same jitted stage-2
    programs (the chunk compiles once for both); a computation field gives new ones."""
    from orgnav_jax.compile_cache import computation_of
    from orgnav_jax.tpn import stage2
    model, _, nav_cfg, _ = loaded
    a = tpn_cfg(base_run, tmp_path / "a")
    b = tpn_cfg(base_run, tmp_path / "b", seed=3, total_episodes=96, tpn_lr=1e-3,
                when="all", eval_every_chunks=2)
    key = lambda c: (computation_of(c, stage2.HOST_ONLY_FIELDS), model,
                     build_tpn(nav_cfg, c.network))
    assert stage2.cached_programs(*key(a)) is stage2.cached_programs(*key(b))
    other = tpn_cfg(base_run, tmp_path / "c", episode_cap=12)
    assert stage2.cached_programs(*key(other)) is not stage2.cached_programs(*key(a))
    chunk = stage2.cached_programs(*key(a))[1]
    train_tpn(a, progress=False)
    train_tpn(b, progress=False)
    assert chunk._cache_size() == 1


def test_cli_trains_and_evaluates_with_tpn(base_run, tmp_path, capsys):
    from orgnav_jax import train as train_cli
    run_dir = tmp_path / "cli-tpn"
    summary = train_cli.main(["--stage", "tpn", "--base", base_run, "--run-dir", str(run_dir),
                              "--num-envs", "8", "--episode-cap", "16", "--total-episodes", "32",
                              "--updates-per-chunk", "2", "--eval-episodes-per-room-type", "2",
                              "--quiet", "--no-test"])
    assert load_tpn_config(run_dir).base_dir == base_run
    assert summary["episodes"] == 32 and (run_dir / "best").exists()
    # every test-time option through the CLI, several to an evaluation (each variant is
    # a program of its own to compile; what the options do is tested in this file,
    # test_tpn_module.py and test_tpn_lowrank.py)
    for variant in ([], ["--when", "all", "--target", "random", "--deadlock", "cosine", "--placement", "state",
                         "--scope", "trunk", "--tpn-lr", "1e-3"],
                    ["--scope", "actor", "--tpn-train-mode", "true", "--reset-every", "0"]):
        out = tmp_path / f"{'-'.join(variant)}.json"
        res = evaluate.main(["--tpn", str(run_dir), "--split", "test", "--quiet",
                             "--episodes-per-room-type", "5", "--out", str(out)] + variant)
        assert res["overall"]["episodes"] == 20 and out.exists()


def test_full_preset_trains_both_stages(base_run, tmp_path):
    """--preset full = ORG + IL (stage 1), then its TPN (stage 2) in one command."""
    from orgnav_jax import train as train_cli
    from orgnav_jax.training.config import load_config
    scenes_dir = load_config(base_run).scenes_dir
    run_dir = tmp_path / "full"
    summary = train_cli.main(["--preset", "full", "--scenes-dir", scenes_dir, "--run-dir",
                              str(run_dir), "--num-envs", "16", "--rollout-len", "8",
                              "--updates-per-chunk", "2", "--total-env-steps", "256",
                              "--eval-episodes-per-room-type", "2", "--tpn-episodes", "64",
                              "--quiet", "--no-test"])
    nav = load_config(run_dir)
    assert (nav.model, nav.il) == ("org", "deadlock")
    tpn = load_tpn_config(run_dir / "tpn")
    assert tpn.base_dir == str(run_dir) and tpn.tpn_lr == TPN_LR
    assert summary["tpn"]["episodes"] >= 64 and (run_dir / "tpn" / "best").exists()


def test_bad_tpn_input_is_a_clear_error(base_run, tpn_run, tmp_path, cli_error):
    from orgnav_jax import train as train_cli
    assert re.search("--base", cli_error(train_cli.main, ["--stage", "tpn"]))
    assert re.search("not a training run", cli_error(
        train_cli.main, ["--stage", "tpn", "--base", str(tmp_path / "nothing")]))
    assert re.search("scope", cli_error(
        train_cli.main, ["--stage", "tpn", "--base", base_run, "--scope", "head"]))
    assert re.search("go with the presets", cli_error(
        train_cli.main, ["--preset", "org_il", "--tpn-lr", "1e-3"]))
    assert re.search("need --tpn", cli_error(
        evaluate.main, ["--checkpoint", base_run, "--when", "all"]))
    with pytest.raises(ValueError, match=r"not a TPN \(stage 2\) run, but a training one"):
        load_tpn_config(base_run)
    assert re.search(r"not a training run, but a TPN \(stage 2\) one", cli_error(
        evaluate.main, ["--checkpoint", tpn_run]))
    assert re.search("'scope': 'head'", cli_error(
        evaluate.main, ["--tpn", tpn_run, "--scope", "head"]))
    with pytest.raises(FileExistsError, match="--resume"):
        train_tpn(load_tpn_config(tpn_run), progress=False)
    from orgnav_jax.training.run_dir import RunLock
    with RunLock(tpn_run):              # another process trains there: refused, named
        assert "is in use by process" in cli_error(
            train_cli.main, ["--stage", "tpn", "--run-dir", tpn_run, "--resume"])


def test_episode_traces_and_pictures_of_a_run_and_a_tpn_run(base_run, tpn_run, tmp_path):
    from orgnav_jax import plots
    for run in (base_run, tpn_run):
        got = plots.trace_run_episode(run, 1, "test", per_room_type=5)
        tr = got["trace"]
        taken = int(tr["running"][0].sum())
        assert taken == int(tr["steps"][0]) >= 1            # one row per action taken
        assert len(got["steps"]["state"]) == taken and got["outcome"] in evaluation.OUTCOMES
        assert sum(bool(tr[k][0]) for k in ("success", "wrong_done", "timeout")) == 1
        rows = got["scenes"].state_slice(int(got["episode"].scene[0]))
        assert np.all((tr["state"][0][:taken] >= rows.start) &
                      (tr["state"][0][:taken] < rows.stop))  # the path stays in its room
        png = tmp_path / f"{Path(run).name}.png"
        assert plots.main(["episode", str(run), "--episode", "1", "--out", str(png)]) == 0
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    assert np.all(np.diff(tr["tpn_updates"][0]) >= 0)        # TPN: a running count


def test_tpn_attention_is_a_top_k_read_of_earlier_steps_and_is_drawn(base_run, tpn_run,
                                                                        tmp_path, capsys,
                                                                        cli_error):
    from orgnav_jax import plots
    top_k = load_tpn_config(tpn_run).top_k
    # the briefly trained base says Done at once; random update targets on every step
    # with a large rate make it act at random, so the episode runs for a while
    att = plots.tpn_attention(tpn_run, 1, "test", per_room_type=5, test_time=dict(
        when="all", target="random", tpn_lr=10.0))
    A = att["attention"]
    T = len(att["updated"])
    assert A.shape == (T, T) and T >= 3
    assert att["updated"].all()                     # when="all": an update on every step
    assert np.all(A >= 0)
    assert np.all(np.triu(A) == 0)                  # step t reads only steps i < t
    np.testing.assert_allclose(A[1:].sum(1), 1.0, rtol=1e-5)   # a softmax from step 1 on
    assert A[0].sum() == 0                          # nothing to read at the first step
    assert np.all((A > 0).sum(1) <= top_k)          # at most k slots weigh
    png = tmp_path / "att.png"
    assert plots.main(["tpn-attention", tpn_run, "--episode", "1", "--step", "2",
                       "--when", "all", "--target", "random", "--tpn-lr", "10",
                       "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    assert "step 2 reads most from steps" in capsys.readouterr().out
    assert "only for a TPN" in cli_error(plots.main, ["tpn-attention", base_run])
    assert "--step 100000" in cli_error(plots.main, ["tpn-attention", tpn_run, "--step", "100000"])


def test_stage2_release_placement_labels_the_step_into_the_deadlock(loaded, base_run,
                                                                    tmp_path):
    """placement "release" (issue 41): the same episodes (same key, frozen base) as the
    state placement; step t is supervised when s_{t+1} is a deadlock, with the expert
    action at s_{t+1}: the state placement's flag and label of step t + 1."""
    model, params, nav_cfg, test = loaded
    batches = {p: collect(model, params, tpn_cfg(base_run, tmp_path / p, episode_cap=20,
                                                 placement=p),
                          test, jax.random.PRNGKey(3), 12) for p in ("state", "release")}
    s, r = ({k: np.asarray(getattr(b, k)) for k in ("valid", "deadlock", "expert", "probs")}
            for b in (batches["state"], batches["release"]))
    np.testing.assert_array_equal(s["valid"], r["valid"])
    np.testing.assert_array_equal(s["probs"], r["probs"])          # the same episodes
    both = s["valid"][:, :-1] & s["valid"][:, 1:]                  # t and t + 1 run
    np.testing.assert_array_equal(r["deadlock"][:, :-1][both], s["deadlock"][:, 1:][both])
    np.testing.assert_array_equal(r["expert"][:, :-1][both], s["expert"][:, 1:][both])
    assert r["deadlock"][:, :-1][both].any() and not r["deadlock"][:, :-1][both].all()
    with pytest.raises(ValueError, match="'release' goes with deadlock 'visited'"):
        get_tpn_config(placement="release", deadlock="cosine")
    cfg = get_tpn_config(optim="release")         # the release's stage-2 optimiser, cap 30
    assert (cfg.lr, cfg.max_grad_norm, cfg.episode_cap) == (1e-4, 100.0, 30)
    assert get_tpn_config() == cfg                 # the default optimiser brings them too
    assert get_tpn_config(optim="ours").lr == 3e-4
    assert get_tpn_config(optim="release", episode_cap=50).episode_cap == 50
