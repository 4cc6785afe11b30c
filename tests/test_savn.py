"""SAVN (training/savn.py): inner steps on the learned loss, the meta-gradient, the fast
weights per episode, the test-time policy and the dsavn preset on the tiny scenes."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import episodes, evaluation
from orgnav_jax.env import EnvParams
from orgnav_jax.models import build_model, init_params, model_inputs
from orgnav_jax.training import savn
from orgnav_jax.training.config import get_config
from orgnav_jax.training.runs import model_policy

TINY_WIDTHS = dict(hidden=8, glob_channels=2, fuse_channels=2, action_embed=3)


@pytest.fixture(scope="module")
def rooms(tiny_scenes):
    return tiny_scenes.split_view("train").to_device()


SMALL = dict(num_envs=3, episode_cap=8, savn_steps=3, savn_inner_steps=2)


def setup(rooms, **kw):
    cfg = get_config("dsavn", scene_preset="tiny", **{**SMALL, **TINY_WIDTHS, **kw})
    model = build_model(cfg, rooms)
    learned = savn.build_learned_loss()
    meta = savn.init_meta(model, learned, cfg, rooms, jax.random.PRNGKey(0))
    return cfg, model, learned, meta


def segment_inputs(rooms, n: int, L: int, seed: int = 0):
    """ModelInputs (n, L, ...) of random states and targets of the rooms."""
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
    states = jax.random.randint(k1, (n * L,), 0, rooms.num_states)
    from orgnav_jax.env import Observation
    C = rooms.present.shape[-1]
    obs = Observation(scene=jnp.zeros(n * L, jnp.int32), state=states,
                      det_box=jnp.zeros((n * L, C, 4)), det_conf=jnp.zeros((n * L, C)),
                      target=jax.nn.one_hot(jax.random.randint(k2, (n * L,), 0, C), C),
                      prev_action=jax.nn.one_hot(jax.random.randint(k3, (n * L,), 0, 6), 6),
                      deadlock=jnp.zeros(n * L, bool))
    inputs = model_inputs(rooms, obs)
    return jax.tree_util.tree_map(lambda x: x.reshape((n, L) + x.shape[1:]), inputs)


def reference_segment(model, variables, carry, inputs):
    """The plain model over L steps of one row (full parameters, step by step), the
    inputs' previous-action entries as given (SAVN's segments hold them as data)."""
    def body(c, x):
        gates = model.apply(variables, jax.tree_util.tree_map(lambda a: a[None], x),
                            method=model.embed)
        logits, _, c, h = model.apply(variables, gates, c, method=model.recur)
        return c, (logits[0], h[0])
    return jax.lax.scan(body, carry, inputs)


def one_row_carry(model):
    return jax.tree_util.tree_map(lambda x: x, model.initial_carry(1))


def test_one_inner_step_is_an_sgd_step_on_the_learned_loss(rooms):
    # two LSTM layers (the rows have one): every layer's kernels are low-rank updates
    cfg, model, learned, meta = setup(rooms, lstm_layers=2)
    nav, k, lr = meta["nav"], cfg.savn_steps, 0.3
    fast = savn.init_fast(nav, 1, 2 * k)
    shared, _ = savn.split_params(nav)
    inputs = jax.tree_util.tree_map(lambda x: x[0], segment_inputs(rooms, 1, k))
    carry = jax.tree_util.tree_map(lambda x: x[0], model.initial_carry(1))
    row = lambda f: jax.tree_util.tree_map(lambda x: x[0], f)
    f = row(fast)
    out = jax.jit(lambda *a: savn.inner_row(model, learned, shared, *a, meta["ll"], lr, 0,
                                            jnp.bool_(True)))(
        f.dense, f.ux, f.uh, f.v, carry, inputs)
    new = savn.Fast(*[jax.tree_util.tree_map(lambda x: x[None], t) for t in out[4:]])
    got = jax.tree_util.tree_map(lambda x: x[0], savn.materialize(nav, new))

    def ll_of(variables):                    # explicit: the learned loss of full weights
        _, (logits, h) = reference_segment(model, variables, model.initial_carry(1), inputs)
        return learned.apply(meta["ll"], savn.learned_input(logits, h))
    g = jax.jit(jax.grad(ll_of))(nav)
    want = jax.tree_util.tree_map(lambda p, d: p - lr * d, nav, g)
    moved = 0
    for a, b, p in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want),
                       jax.tree_util.tree_leaves(nav)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
        moved += int(not np.allclose(a, p))
    assert moved >= 8
    # the segment's own forward pass is the plain model's
    _, (logits, _) = jax.jit(lambda v, x: reference_segment(
        model, v, model.initial_carry(1), x))(nav, inputs)
    np.testing.assert_allclose(out[0], logits, rtol=1e-5, atol=1e-6)


def test_meta_gradient_matches_finite_differences(rooms):
    """Two segments: an inner step on the first, an outer loss on the second's logits and
    values; the gradient w.r.t. the initial parameters and the learned loss (second order,
    float64) against central differences along a random direction. Two LSTM layers (the
    rows have one): the second-order gradient through both layers' low-rank updates."""
    cfg, model, learned, meta32 = setup(rooms, hidden=4, lstm_layers=2)
    k = cfg.savn_steps
    seg32 = segment_inputs(rooms, 1, 2 * k, seed=3)
    with jax.enable_x64(True):
        def objective(m, seg, first_order=False):
            first = jax.tree_util.tree_map(lambda x: x[:k], seg)
            second = jax.tree_util.tree_map(lambda x: x[k:], seg)
            shared, _ = savn.split_params(m["nav"])
            f = jax.tree_util.tree_map(lambda x: x[0], savn.init_fast(m["nav"], 1, k))
            carry = jax.tree_util.tree_map(lambda x: x[0].astype(jnp.float64),
                                           model.initial_carry(1))
            _, _, carry, _, dense, ux, uh, v = savn.inner_row(
                model, learned, shared, f.dense, f.ux, f.uh, f.v, carry, first, m["ll"], 0.5,
                0, jnp.bool_(True), first_order)
            logits, values, *_ = savn.segment_row(model, shared, dense, ux, uh, v, carry,
                                                  second, tuple(jnp.zeros((k, w.shape[-1]))
                                                                for w in v))
            return jnp.sum(jnp.sin(jnp.arange(6.0) + 1) * jax.nn.log_softmax(logits)) + \
                jnp.sum(values ** 2)

        @jax.jit              # everything in one program: one compile, no op-by-op float64
        def check(meta32, seg32):
            f64 = lambda t: jax.tree_util.tree_map(
                lambda x: x.astype(jnp.float64) if jnp.issubdtype(x.dtype, jnp.floating)
                else x, t)
            meta, seg = f64(meta32), jax.tree_util.tree_map(lambda x: x[0], f64(seg32))
            leaves, tree = jax.tree_util.tree_flatten(meta)
            keys = jax.random.split(jax.random.PRNGKey(7), len(leaves))
            direction = tree.unflatten([jax.random.normal(kk, x.shape, jnp.float64)
                                        for kk, x in zip(keys, leaves)])
            eps = 1e-5
            shift = lambda s: jax.tree_util.tree_map(lambda x, d: x + s * d, meta, direction)
            fd = (objective(shift(eps), seg) - objective(shift(-eps), seg)) / (2 * eps)
            second = jax.grad(objective)(meta, seg, False)
            first = jax.grad(objective)(meta, seg, True)
            analytic = sum(jnp.vdot(g, d) for g, d in zip(
                jax.tree_util.tree_leaves(second), jax.tree_util.tree_leaves(direction)))
            ll_norm = lambda g: sum(jnp.abs(x).sum() for x in jax.tree_util.tree_leaves(
                g["ll"]))
            return analytic, fd, ll_norm(second), ll_norm(first)

        # random biases: the release's zero biases put undetected categories' maps exactly
        # on their ReLU's kink, where central differences average the two one-sided slopes
        leaves, tree = jax.tree_util.tree_flatten_with_path(meta32)
        keys = jax.random.split(jax.random.PRNGKey(11), len(leaves))
        meta32 = tree.unflatten([x + 0.1 * jax.random.normal(kk, x.shape)
                                 if "bias" in str(path[-1]) else x
                                 for (path, x), kk in zip(leaves, keys)])
        analytic, fd, ll_second, ll_first = check(meta32, seg32)
        assert analytic.dtype == jnp.float64
        np.testing.assert_allclose(analytic, fd, rtol=1e-6)
        # the learned loss gets a meta-gradient (second order), none with first order
        assert float(ll_second) > 0
        assert float(ll_first) == 0


def test_fast_weights_never_leak_across_rows_or_episodes(rooms):
    cfg, model, learned, meta = setup(rooms)
    nav, k = meta["nav"], cfg.savn_steps
    shared, _ = savn.split_params(nav)
    fast = savn.init_fast(nav, 3, 2 * k)
    inputs = segment_inputs(rooms, 3, k)
    carry = model.initial_carry(3)
    # the trainer's batch form: one gradient of the rows' summed learned losses
    v_inner = jax.jit(lambda d, ux, uh, v, c, x, on: savn.inner_rows(
        model, learned, shared, d, ux, uh, v, c, x, meta["ll"], 0.5, jnp.zeros(3, jnp.int32),
        on))
    on = jnp.array([True, False, True])
    out = v_inner(fast.dense, fast.ux, fast.uh, fast.v, carry, inputs, on)
    new = savn.Fast(*out[4:])
    # ... is each row's own step: row 2 alone gives the same fast weights
    alone = savn.inner_row(model, learned, shared, *jax.tree_util.tree_map(
        lambda x: x[2], (fast.dense, fast.ux, fast.uh, fast.v, carry, inputs)), meta["ll"],
        0.5, 0, True)
    for a, b in zip(jax.tree_util.tree_leaves(alone[4:]), jax.tree_util.tree_leaves(out[4:])):
        np.testing.assert_allclose(a, b[2], rtol=1e-5, atol=1e-7)
    weights = savn.materialize(nav, new)
    base = savn.materialize(nav, fast)
    row = lambda t, i: [np.asarray(x[i]) for x in jax.tree_util.tree_leaves(t)]
    assert all(np.array_equal(a, b) for a, b in zip(row(weights, 1), row(base, 1)))
    assert not all(np.allclose(a, b) for a, b in zip(row(weights, 0), row(base, 0)))
    # another row's inputs do not change row 0's update
    other = jax.tree_util.tree_map(lambda x: x.at[2].set(x[1]), inputs)
    out2 = v_inner(fast.dense, fast.ux, fast.uh, fast.v, carry, other, on)
    w2 = savn.materialize(nav, savn.Fast(*out2[4:]))
    assert all(np.array_equal(a, b) for a, b in zip(row(w2, 0), row(weights, 0)))
    # a new episode starts from the trained weights
    reset = savn.reset_fast(nav, new, jnp.array([True, False, False]))
    assert all(np.array_equal(a, b) for a, b in zip(row(savn.materialize(nav, reset), 0),
                                                    row(base, 0)))


def _val_episodes(rooms_val):
    return episodes.sample_episodes(rooms_val, 3, seed=0, split="val")


def test_inner_lr_zero_equals_the_base_model_and_evaluation_is_deterministic(tiny_scenes):
    val = tiny_scenes.split_view("val").to_device()
    eps = _val_episodes(val)
    cfg, model, learned, meta = setup(val)
    params = EnvParams.evaluation()
    base = evaluation.trace_episodes(model_policy(model), meta["nav"], val, eps, params)
    zero = savn.savn_policy(model, learned, cfg.savn_steps, 4, 0.0, savn.scene_widths(val))
    got = evaluation.trace_episodes(zero, meta, val, eps, params)
    np.testing.assert_array_equal(got["action"], base["action"])
    np.testing.assert_array_equal(got["success"], base["success"])
    # with inner steps: different actions somewhere, the same for the same seed
    meta_big = dict(meta, ll=jax.tree_util.tree_map(lambda x: 30 * x, meta["ll"]))
    pol = savn.savn_policy(model, learned, cfg.savn_steps, 4, 3.0, savn.scene_widths(val))
    a = evaluation.trace_episodes(pol, meta_big, val, eps, params)
    b = evaluation.trace_episodes(pol, meta_big, val, eps, params)
    np.testing.assert_array_equal(a["action"], b["action"])
    assert (a["action"] != base["action"]).any()


# The CLI test below trains this computation, so the two share one compiled chunk
# (the trainer's cache, loop.cached_savn_chunk). 3 segments per update, not the default
# 5: savn_loss unrolls its segments (savn.unrolled), so the program's compile grows with
# them; 3 still refill rows at two boundaries per update (an episode of the cap, 8 steps,
# spans 3 segments of 3: every row ends at least 2 episodes in a chunk's 6 segments).
CHUNK_FIELDS = dict(SMALL, updates_per_chunk=2, savn_segments=3)


def test_the_chunk_compiles_once(rooms):
    from orgnav_jax.training import loop
    cfg, model, _, _ = setup(rooms, **CHUNK_FIELDS)
    optimizer, learned, chunk = loop.cached_savn_chunk(loop.compute_config(cfg), model)
    runner = savn.init_savn_runner(cfg, model, learned, optimizer, rooms, jax.random.PRNGKey(1))
    before = jax.tree_util.tree_leaves(runner.params)
    for _ in range(3):
        runner, metrics = chunk(runner, rooms)
    assert chunk._cache_size() == 1
    assert loop.cached_savn_chunk(loop.compute_config(cfg), model)[2] is chunk
    assert bool(metrics["loss_finite"]) and int(runner.update) == 6
    # rows refilled at segment boundaries: more episodes end than there are rows
    assert float(metrics["episodes"]) > cfg.num_envs
    assert 0 < float(metrics["env_steps_real"]) <= 2 * cfg.steps_per_update
    assert any(not np.allclose(a, b) for a, b in zip(before,
                                                     jax.tree_util.tree_leaves(runner.params)))


REFILL = dict(num_envs=6, savn_segments=5, savn_inner_lr=3.0)


def test_a_refilled_row_starts_a_new_episode_with_the_meta_weights(rooms):
    """At the segment boundary after a row's episode ended, the row starts a new episode
    with the meta-parameters (no slot of the last episode's inner steps left), a zero LSTM
    carry and no inner step taken; the new episode acts as the plain model of the
    meta-parameters would (nothing of the last episode leaks into it), and it takes its
    own inner steps. Episodes still running at the update's end go on in the next update
    with their carry, env state, inner-step count and fast weights as offsets over the
    new meta-parameters."""
    cfg, model, learned, meta = setup(rooms, **REFILL)
    meta = dict(meta, ll=jax.tree_util.tree_map(lambda x: 30 * x, meta["ll"]))
    rows = savn.init_rows(cfg, model, meta["nav"], rooms, jax.random.PRNGKey(3))
    loss = jax.jit(lambda m, r, key: savn.savn_loss(m, r, model, learned, cfg, rooms, key,
                                                    trace=True))
    _, (aux, stats, rows1) = loss(meta, rows, jax.random.PRNGKey(4))
    tr = jax.tree_util.tree_map(np.asarray, aux["trace"])
    nav = meta["nav"]
    leaves = lambda t, r: [np.asarray(x[r]) for x in jax.tree_util.tree_leaves(t)]
    trained = [np.asarray(x) for x in jax.tree_util.tree_leaves(nav)]
    plain = jax.jit(lambda x: reference_segment(model, nav, one_row_carry(model), x)[1][0])
    assert tr["new"][0].all()                          # every row starts at the first
    checked = 0
    for s in range(1, cfg.savn_segments):
        for r in np.flatnonzero(tr["new"][s]):
            if tr["updates"][s - 1, r] == 0:         # the last episode took no inner step
                continue
            checked += 1
            before = savn.materialize(nav, jax.tree_util.tree_map(lambda x: x[s - 1], tr[
                "fast"]))
            assert not all(np.allclose(a, b) for a, b in zip(leaves(before, r), trained))
            after = savn.materialize(nav, jax.tree_util.tree_map(lambda x: x[s], tr["fast"]))
            assert all(np.array_equal(a, b) for a, b in zip(leaves(after, r), trained))
            assert all((x[s, r] == 0).all() for x in jax.tree_util.tree_leaves(tr["lstm"]))
            assert tr["updates"][s, r] == 0
            want = plain(jax.tree_util.tree_map(lambda x: x[s, r], tr["inputs"]))
            np.testing.assert_allclose(tr["logits"][s][:, r], want, rtol=1e-5, atol=1e-6)
    assert checked >= 2, checked
    # a refilled episode that runs on takes its own first inner step after its segment
    U, N = cfg.savn_segments, cfg.num_envs
    assert any(tr["new"][s, r] and not tr["new"][s + 1, r] and tr["updates"][s + 1, r] == 1
               for s in range(1, U - 1) for r in range(N))
    assert float(stats.count) >= cfg.num_envs
    # an episode running at the update's end goes on in the next update
    going = np.flatnonzero(np.asarray(rows1.running) & (np.asarray(rows1.updates) > 0))
    assert going.size
    nav2 = jax.tree_util.tree_map(lambda x: x + 0.01, nav)
    _, (aux2, _, _) = loss(dict(meta, nav=nav2), rows1, jax.random.PRNGKey(5))
    tr2 = jax.tree_util.tree_map(np.asarray, aux2["trace"])
    first = lambda t: jax.tree_util.tree_map(lambda x: x[0], t)
    for r in going:
        assert not tr2["new"][0, r] and tr2["updates"][0, r] == rows1.updates[r]
        assert all(np.array_equal(a[0, r], b[r]) for a, b in zip(
            jax.tree_util.tree_leaves(tr2["lstm"]), jax.tree_util.tree_leaves(rows1.lstm)))
        # its fast weights: the new meta-parameters plus what its inner steps changed
        moved2 = [a - b for a, b in zip(leaves(savn.materialize(nav2, first(tr2["fast"])),
                                               r),
                                        [np.asarray(x) for x in
                                         jax.tree_util.tree_leaves(nav2)])]
        moved1 = [a - b for a, b in zip(leaves(savn.materialize(
            nav, savn.fast_over(nav, rows1.delta)), r), trained)]
        for a, b in zip(moved2, moved1):
            np.testing.assert_allclose(a, b, atol=1e-5)
        assert any(np.abs(b).max() > 0 for b in moved1)


def test_dsavn_preset_trains_and_evaluates_from_the_cli(tiny_dir, tmp_path):
    """(chunks of the computation of the compiles-once test: its program is reused.) The
    budget counts the env steps the episodes really took (issue 40): the run stops at the
    first chunk whose running count reaches it, each record's env_steps is that count, and
    a resumed run with a larger budget continues the same count."""
    from orgnav_jax.errors import run_cli
    from orgnav_jax.train import main
    from orgnav_jax.training.config import CONFIG_VERSION
    run = tmp_path / "dsavn"
    argv = ["--preset", "dsavn", "--scenes-dir", tiny_dir, "--run-dir", str(run),
            "--total-env-steps", "60", "--eval-every-chunks", "2",
            "--eval-episodes-per-room-type", "2", "--quiet", "--no-test",
            *sum(([f"--{k.replace('_', '-')}", str(v)]
                  for k, v in {**TINY_WIDTHS, **CHUNK_FIELDS}.items()), [])]
    assert run_cli(main, argv) == 0
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["savn"] and cfg["model"] == "baseline" and cfg["version"] == CONFIG_VERSION

    def train_records():
        records = [json.loads(line) for line in
                   (run / "metrics.jsonl").read_text().splitlines()]
        return [r for r in records if "env_steps_real" in r]

    def check_counts(train, budget):
        real = [r["env_steps_real"] for r in train]
        assert all(0 < x <= 2 * 3 * 3 * 3 for x in real)   # 2 updates x 3 rows x 3 x 3
        assert [r["env_steps"] for r in train] == list(np.cumsum(real).astype(int))
        assert train[-1]["env_steps"] >= budget > (train[-2]["env_steps"] if len(train) > 1
                                                   else 0)

    first = train_records()
    check_counts(first, 60)
    assert run_cli(main, ["--run-dir", str(run), "--resume", "--total-env-steps", "120",
                          "--quiet", "--no-test"]) == 0
    again = train_records()
    assert again[:len(first)] == first and len(again) > len(first)
    check_counts(again, 120)
    assert (run / "best").is_dir()
    from orgnav_jax.training.runs import load_run_policy
    policy, params, loaded = load_run_policy(run)
    assert loaded.savn and set(params) == {"nav", "ll"} and "SAVN" in policy.name


@pytest.mark.parametrize("version, says", [(6, "episode slots"),
                                           (7, "stepped every episode whole"),
                                           (8, "first LSTM layer's updates low-rank")])
def test_resuming_a_savn_run_of_an_older_meaning_is_refused(tmp_path, capsys, version,
                                                            says):
    """A SAVN run of config version <= 6 counted every episode at its cap; one of version
    7 stepped whole episodes (its checkpoints hold no running episodes); one of version 8
    holds its running episodes' fast weights in another layout: resuming any of them is
    one line, exit 2, before anything is written."""
    from orgnav_jax.errors import run_cli
    from orgnav_jax.train import main
    from orgnav_jax.training.config import get_config
    run = tmp_path / "old"
    run.mkdir()
    doc = {k: v for k, v in json.loads(get_config("dsavn").to_json()).items()
           if k != "savn_segments"}
    doc.update(version=version, run_dir=str(run))
    (run / "config.json").write_text(json.dumps(doc))
    before = sorted(p.name for p in run.iterdir())
    assert run_cli(main, ["--run-dir", str(run), "--resume", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0] and f"config version {version}" in err[0], err
    assert sorted(p.name for p in run.iterdir()) == before


@pytest.mark.parametrize("version", [7, 8])
def test_an_older_savn_run_still_loads_from_its_latest_checkpoint(tiny_dir, tmp_path,
                                                                  version):
    """A SAVN run saved before the refill (config version 7) has no rows in its runner;
    one of version 8 (two LSTM layers here) holds its rows' fast weights with the second
    layer's updates dense (savn.legacy_rows): the latest checkpoint of either (no best
    one) still gives its parameters for evaluation."""
    from orgnav_jax.training import runs
    from orgnav_jax.training.checkpoints import RunCheckpoints
    from orgnav_jax.training.update import make_optimizer
    run = tmp_path / f"v{version}"
    run.mkdir()
    cfg = get_config("dsavn", scenes_dir=tiny_dir, run_dir=str(run), lstm_layers=2,
                     **{**SMALL, **TINY_WIDTHS})
    doc = json.loads(cfg.to_json())
    if version < 8:
        doc.pop("savn_segments")
    (run / "config.json").write_text(json.dumps(dict(doc, version=version)))
    scenes = runs.scenes_for(cfg).split_view("train")
    model = build_model(cfg, scenes)
    runner = savn.init_savn_runner(cfg, model, savn.build_learned_loss(), make_optimizer(cfg),
                                   scenes.to_device(), jax.random.PRNGKey(2))
    rows = None if version < 8 else savn.legacy_rows(runner.rows)
    RunCheckpoints(run).save(48, runner.replace(rows=rows), {"chunk": 1, "best": {}})
    _, params, loaded = runs.load_run_model(run, best=False)
    assert loaded.savn
    for a, b in zip(jax.tree_util.tree_leaves(params),
                    jax.tree_util.tree_leaves(runner.params)):
        np.testing.assert_array_equal(a, b)
