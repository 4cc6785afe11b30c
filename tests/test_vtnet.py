"""VTNet (issue 43): the position embedding, the attention masks, the decoder's one vector
per map cell, the exact first decoder layer, float32 attention under bf16, the
initialisations, the pre-trained parameters' learning rate, and one tiny run of both
stages from the command line (pre-training lowers the val cross-entropy; the A2C run
starts from its parameters; errors in one line)."""

from __future__ import annotations

import json
import math
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import scenes as scenes_mod
from orgnav_jax import train as train_cli
from orgnav_jax.models import build_model, init_params
from orgnav_jax.models.navmodel import feature_widths
from orgnav_jax.models.vtnet import (
    DecoderLayer, VTNetPretrain, attention_weights, is_visual, position_embedding)
from orgnav_jax.training.config import get_config

C = 22


def _path(path) -> str:
    return "/".join(str(getattr(p, "key", p)) for p in path)


# ------------------------------------------------------------------ position embedding

def test_position_embedding_matches_a_hand_computation():
    """The release's get_gloabal_pos_embedding(7, c): cell (r, c) is row r * 7 + c; the
    first half from y = r + 1, the second from x = c + 1; channel i is sin (even i) or cos
    (odd i) of coord / 10000 ** (2 * (i // 2) / c)."""
    pos = position_embedding(7, 4)                       # d_model 8
    assert pos.shape == (49, 8) and pos.dtype == np.float32
    r, c = 2, 5
    y, x = 3.0, 6.0
    want = [math.sin(y), math.cos(y), math.sin(y / 100), math.cos(y / 100),
            math.sin(x), math.cos(x), math.sin(x / 100), math.cos(x / 100)]
    np.testing.assert_allclose(pos[r * 7 + c], want, rtol=1e-6, atol=1e-7)
    full = position_embedding()                          # the release's (7, 128): 256
    assert full.shape == (49, 256)
    np.testing.assert_allclose(full[0, :2], [math.sin(1), math.cos(1)], rtol=1e-6)
    np.testing.assert_allclose(full[48, 128 + 126], math.sin(7 / 10000 ** (126 / 128)),
                               rtol=1e-5)
    assert len({tuple(row) for row in full.round(6)}) == 49      # every cell its own


# ------------------------------------------------------------------ attention and masks

def test_attention_weights_masked_keys_get_nothing_and_empty_rows_no_nan():
    q = jax.random.normal(jax.random.PRNGKey(0), (2, 1, 3, 4))
    k = jax.random.normal(jax.random.PRNGKey(1), (2, 1, 5, 4))
    keep = jnp.array([[True, False, True, False, True], [False] * 5])
    w = np.asarray(attention_weights(q, k, keep))
    assert w.dtype == np.float32 and np.isfinite(w).all()
    np.testing.assert_allclose(w[0].sum(-1), 1.0, rtol=1e-6)
    assert (w[0][..., [1, 3]] == 0).all()
    assert (w[1] == 0).all()                     # no key kept: zero output, not NaN
    plain = np.asarray(attention_weights(q, k))
    scores = np.einsum("bhqd,bhkd->bhqk", np.asarray(q), np.asarray(k)) / 2.0
    e = np.exp(scores - scores.max(-1, keepdims=True))
    np.testing.assert_allclose(plain, e / e.sum(-1, keepdims=True), rtol=1e-5)


@pytest.fixture(scope="module")
def tiny_train(tiny_scenes):
    return tiny_scenes.split_view("train").to_device()


@pytest.fixture(scope="module")
def batch(tiny_train):
    """Model inputs of 4 random states of the tiny training rooms."""
    from orgnav_jax.training.pretrain import sample_batch
    inputs, _ = jax.jit(sample_batch, static_argnums=2)(tiny_train, jax.random.PRNGKey(3), 4)
    return inputs


def _decode(model, params, inputs):
    """The decoder's output (B, 49, dim) and the per-cell representation (B, 49, R)."""
    return _decode_jit(model, params, inputs)


@partial(jax.jit, static_argnums=0)
def _decode_jit(model, params, inputs):       # one program per model (hashable, static)
    def f(m, i):
        tokens, keep = m.encoder(i.app, i.box, i.conf, i.target)
        return m.trunk.decode(i.glob, tokens, keep), m.trunk.visual(i.glob, tokens, keep)
    return model.apply(params, inputs, method=f)


@pytest.mark.parametrize("mask", ["none", "undetected"])
def test_masks_undetected_categories_as_documented(tiny_train, batch, mask):
    """The release masks nothing: an undetected category's token (appearance 0 in real
    inputs; here made non-zero) changes every cell's vector. vtnet_mask 'undetected'
    drops undetected non-target categories from the keys: the same change does nothing,
    while the target's token counts detected or not."""
    cfg = get_config("tiny", model="vtnet", vtnet_mask=mask)
    model = build_model(cfg, tiny_train)
    params = init_params(model, jax.random.PRNGKey(0), tiny_train)
    conf = np.asarray(batch.conf).copy()
    target = np.asarray(batch.target).argmax(-1)
    c = next(i for i in range(C) if i != target[0])
    conf[0, c] = 0.0                                       # c undetected in sample 0
    inputs = batch._replace(conf=jnp.asarray(conf))
    app = np.asarray(inputs.app).copy()
    app[0, c] = 3.0 * np.random.default_rng(0).standard_normal(app.shape[-1])
    out, _ = _decode(model, params, inputs)
    moved, _ = _decode(model, params, inputs._replace(app=jnp.asarray(app)))
    diff = np.abs(np.asarray(moved[0]) - np.asarray(out[0])).max(-1)       # per cell
    if mask == "none":
        assert (diff > 1e-5).all()
    else:
        assert (diff < 1e-5).all()
        conf[0, target[0]] = 0.0                         # the target undetected too
        t_in = inputs._replace(conf=jnp.asarray(conf))
        other = np.zeros_like(np.asarray(batch.target))
        other[0, c] = 1.0                                # ... and another target
        a, _ = _decode(model, params, t_in)
        b, _ = _decode(model, params, t_in._replace(target=jnp.asarray(other)))
        assert np.abs(np.asarray(a[0]) - np.asarray(b[0])).max() > 1e-5


def test_the_decoder_returns_one_vector_per_map_cell(tiny_train, batch):
    """(B, 49, dim) from the decoder, (B, 49, R) per cell after 256 -> 128 -> 64; with one
    decoder layer (no self-attention between the queries: the first one is constant) a
    change of the global map at one cell moves that cell's vector only."""
    cfg = get_config("tiny", model="vtnet")
    model = build_model(cfg, tiny_train)
    params = init_params(model, jax.random.PRNGKey(0), tiny_train)
    dec, rep = _decode(model, params, batch)
    assert dec.shape == (4, 49, cfg.vtnet_dim) and rep.shape == (4, 49, cfg.fuse_channels)
    flat = np.asarray(dec[0]).round(5)
    assert len({tuple(row) for row in flat}) == 49
    glob = np.asarray(batch.glob).copy()
    glob[0, 3, 4] += 1.0                                 # cell 3 * 7 + 4
    moved, _ = _decode(model, params, batch._replace(glob=jnp.asarray(glob)))
    diff = np.abs(np.asarray(moved) - np.asarray(dec)).max(-1)
    assert diff[0, 25] > 1e-4 and np.delete(diff[0], 25).max() < 1e-6
    assert diff[1:].max() == 0


def test_the_first_decoder_layers_constant_self_attention_is_exact():
    """With target 0 the self-attention's output is out_proj(b_v) for every query: the
    shortcut equals the full layer (random biases, so b_v matters)."""
    D, L = 8, 49
    layer = DecoderLayer(D, 2, 16)
    t = jnp.zeros((2, L, D))
    mem = jax.random.normal(jax.random.PRNGKey(1), (2, 5, D))
    qpos = jax.random.normal(jax.random.PRNGKey(2), (2, L, D))
    @jax.jit
    def init(key):         # random biases too (init zeroes them), so b_v matters
        params = layer.init(key, t, mem, qpos)
        leaves, tree = jax.tree_util.tree_flatten(params)
        keys = jax.random.split(jax.random.fold_in(key, 1), len(leaves))
        return jax.tree_util.tree_unflatten(tree, [
            x + 0.3 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])
    params = init(jax.random.PRNGKey(0))
    apply = jax.jit(layer.apply, static_argnames="first")
    full = apply(params, t, mem, qpos, first=False)
    fast = apply(params, t, mem, qpos, first=True)
    np.testing.assert_allclose(np.asarray(fast), np.asarray(full), atol=2e-6)


def test_vtnet_attention_runs_in_float32_under_bfloat16(tiny_train, batch):
    """--dtype bfloat16: the matmuls take bf16 operands, the attention weights (scores,
    softmax) are float32 and sum to 1 to float32 precision; the outputs agree with the
    float32 model's to bf16 precision; parameters stay float32."""
    q = jax.random.normal(jax.random.PRNGKey(0), (2, 1, 49, 16)).astype(jnp.bfloat16)
    k = jax.random.normal(jax.random.PRNGKey(1), (2, 1, 22, 16)).astype(jnp.bfloat16)
    w = attention_weights(q, k)
    assert w.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(w.sum(-1)), 1.0, atol=1e-6)
    out = {}
    params = init_params(build_model(get_config("tiny", model="vtnet"), tiny_train),
                         jax.random.PRNGKey(0), tiny_train)   # the same for both dtypes
    assert {str(x.dtype) for x in jax.tree_util.tree_leaves(params)} == {"float32"}
    for dtype in ("float32", "bfloat16"):
        model = build_model(get_config("tiny", model="vtnet", dtype=dtype), tiny_train)
        fn = jax.jit(lambda p, i, m=model: m.apply(p, i, m.initial_carry(4))[:2])
        hlo = fn.lower(params, batch).as_text()
        out[dtype] = fn(params, batch), hlo
    (l32, v32), hlo32 = out["float32"]
    (l16, v16), hlo16 = out["bfloat16"]
    assert "bf16" in hlo16 and "bf16" not in hlo32
    assert l16.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(l16), np.asarray(l32), atol=2e-3)
    np.testing.assert_allclose(np.asarray(v16), np.asarray(v32), rtol=0.05, atol=2e-3)


# ------------------------------------------------------------------ initialisations

def test_initialisations_follow_the_release(tiny_train, batch):
    """A2C (VTNetModel: weights_init): every kernel Glorot uniform, biases 0, the global
    1x1 times the ReLU gain, the actor's columns of norm 0.01. Pre-training
    (PreTrainedVisualTransformer, no weights_init): torch's defaults outside the
    transformer (non-zero biases), Glorot inside it, attention biases 0."""
    cfg = get_config("tiny", model="vtnet")
    model = build_model(cfg, tiny_train)
    params = init_params(model, jax.random.PRNGKey(0), tiny_train)
    flat = {_path(p): np.asarray(x) for p, x in jax.tree_util.tree_leaves_with_path(params)}
    for name, x in flat.items():
        if name.endswith("/bias"):
            assert (x == 0).all(), name
    g = flat["params/trunk/global_1x1/kernel"]
    assert np.abs(g).max() > math.sqrt(6 / sum(g.shape)) * 1.05
    np.testing.assert_allclose(np.linalg.norm(flat["params/trunk/actor/kernel"], axis=0),
                               0.01, rtol=1e-5)
    from orgnav_jax.training.pretrain import pretrain_init
    net = VTNetPretrain(model.encoder, model.trunk)
    pre = jax.jit(lambda i: pretrain_init(net.init({"params": jax.random.PRNGKey(0)}, i),
                                          jax.random.PRNGKey(1)))(batch)
    flat = {_path(p): np.asarray(x) for p, x in jax.tree_util.tree_leaves_with_path(pre)}
    assert not (flat["params/encoder/local_0/bias"] == 0).all()
    assert not (flat["params/pretrain_fc/bias"] == 0).all()
    assert (flat["params/encoder/layer_0/self_attn/bias"] == 0).all()
    assert not (flat["params/encoder/layer_0/ffn/linear1/bias"] == 0).all()
    k = flat["params/encoder/layer_0/self_attn/kernel"]           # (D, 3D): xavier on it
    assert np.abs(k).max() <= math.sqrt(6 / sum(k.shape))
    assert "params/trunk/lstm_0/input_kernel" not in flat          # visual part only
    assert feature_widths(params) == {"global_dim": tiny_train.global_dim,
                                      "appearance_dim": tiny_train.appearance_dim}


def test_pretrained_parameters_step_at_the_scaled_learning_rate(tiny_train):
    """With pretrained set, an Adam step of the visual parameters is pretrained_lr_scale
    times the step the others take for the same gradient (the release's two groups)."""
    from orgnav_jax.training.update import make_optimizer
    cfg = get_config("tiny", model="vtnet")
    params = init_params(build_model(cfg, tiny_train), jax.random.PRNGKey(0), tiny_train)
    grads = jax.tree_util.tree_map(jnp.ones_like, params)
    plain = make_optimizer(cfg)
    scaled = make_optimizer(get_config("tiny", model="vtnet", pretrained="somewhere"))
    step = lambda opt: jax.jit(lambda g, p: opt.update(g, opt.init(p), p)[0])(grads, params)
    u0, u1 = step(plain), step(scaled)
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(u0),
                            jax.tree_util.tree_leaves(u1)):
        factor = cfg.pretrained_lr_scale if is_visual(_path(path)[len("params/"):]) else 1.0
        np.testing.assert_allclose(np.asarray(b), factor * np.asarray(a), rtol=1e-6)


# ------------------------------------------------------------------ both stages, CLI

SMALL = ["--num-envs", "16", "--rollout-len", "8", "--updates-per-chunk", "2",
         "--total-env-steps", str(2 * 16 * 8 * 2), "--eval-every-chunks", "2",
         "--eval-episodes-per-room-type", "2", "--checkpoint-every-chunks", "5",
         "--pretrain-batch", "64", "--pretrain-samples", str(64 * 2 * 10),
         "--pretrain-val-samples", "512", "--quiet", "--no-test"]


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory, tiny_dir):
    """`--preset vtnet` on the tiny scenes: 10 chunks of pre-training (64 x 2 samples
    each, val every 2; the val cross-entropy drops from ~1.79 to ~1.44 by then and levels
    off near 1.33 after ~2000 samples), then 2 chunks of A2C from it."""
    root = tmp_path_factory.mktemp("vtnet")
    run = root / "run"
    summary = train_cli.main(["--preset", "vtnet", "--scenes-dir", tiny_dir,
                              "--run-dir", str(run), *SMALL])
    return root, run, summary


def _records(run_dir, kind):
    lines = (Path(run_dir) / "metrics.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["kind"] == kind]


def test_cli_pretrains_then_trains_from_it(cli_run):
    root, run, summary = cli_run
    pre = Path(f"{run}-pretrain")
    saved = json.loads((pre / "config.json").read_text())
    assert saved["stage"] == "pretrain" and saved["model"] == "vtnet"
    val = _records(pre, "val")
    assert len(val) == 5 and all({"accuracy", "ce"} <= set(r) for r in val)
    assert [r["samples"] for r in val] == [256 * (i + 1) for i in range(5)]
    assert summary["pretrain"]["samples"] == 64 * 2 * 10
    nav = json.loads((run / "config.json").read_text())
    assert nav.get("stage", "nav") == "nav" and nav["pretrained"] == str(pre)
    assert summary["env_steps"] == 2 * 16 * 8 * 2 and (run / "best").is_dir()
    assert _records(run, "val")


def test_pretraining_lowers_the_val_cross_entropy(cli_run, tiny_dir):
    """The val cross-entropy of the expert actions after the tiny pre-training is below
    that of the initial network (the same val draw; the programs the run compiled)."""
    from orgnav_jax.compile_cache import computation_of
    from orgnav_jax.training import pretrain as P
    root, run, _ = cli_run
    cfg = P.load_pretrain_config(f"{run}-pretrain")
    scenes = scenes_mod.load(tiny_dir)
    train, val = (scenes.split_view(s).to_device() for s in ("train", "val"))
    net = P.pretrain_network(cfg, train)
    _, init, _, val_fn = P.cached_programs(computation_of(cfg, P.HOST_ONLY_FIELDS), net)
    inputs, labels = P.val_set(cfg, val)
    k_init, _ = jax.random.split(jax.random.PRNGKey(cfg.seed))
    before = float(val_fn(init(k_init, train), inputs, labels)["ce"])
    after = _records(f"{run}-pretrain", "val")[-1]["ce"]
    assert after < before - 0.05, (before, after)


def test_the_a2c_run_starts_from_the_pretrained_parameters(cli_run, tiny_dir):
    """start_from_pretrained: the visual leaves are the pre-training's best-on-val ones,
    the rest (action row, LSTM, heads) the fresh initialisation's."""
    from orgnav_jax.training.checkpoints import RunCheckpoints
    from orgnav_jax.training.config import load_config
    from orgnav_jax.training.loop import start_from_pretrained
    from orgnav_jax.training.update import init_runner, make_optimizer
    root, run, _ = cli_run
    cfg = load_config(run)
    train = scenes_mod.load(tiny_dir).split_view("train").to_device()
    model = build_model(cfg, train)
    fresh = init_runner(cfg, model, make_optimizer(cfg), train, jax.random.PRNGKey(0))
    started = start_from_pretrained(cfg, fresh, resume=False)
    from orgnav_jax.training import pretrain as P
    net = P.pretrain_network(P.load_pretrain_config(cfg.pretrained), train)
    inputs, _ = P.sample_batch(train, jax.random.PRNGKey(0), 1)
    like = jax.eval_shape(lambda: net.init({"params": jax.random.PRNGKey(0)}, inputs))
    saved, _ = RunCheckpoints(cfg.pretrained).restore(like, best=True)
    have = {_path(p): np.asarray(x)
            for p, x in jax.tree_util.tree_leaves_with_path(saved["params"])}
    n_visual = 0
    for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(started.params["params"]),
                            jax.tree_util.tree_leaves(fresh.params["params"])):
        name = _path(path)
        if is_visual(name):
            np.testing.assert_array_equal(np.asarray(a), have[name])
            n_visual += 1
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert n_visual > 20


def test_pretraining_resumes_to_a_larger_budget(cli_run, capsys):
    root, run, _ = cli_run
    pre = f"{run}-pretrain"
    out = train_cli.main(["--stage", "pretrain", "--resume", "--run-dir", pre,
                          "--pretrain-samples", str(64 * 2 * 12), "--quiet"])
    assert out["samples"] == 64 * 2 * 12 and out["chunks"] == 12
    samples = [r["samples"] for r in _records(pre, "train")]
    assert samples == [128 * (i + 1) for i in range(12)]


class _Stop(Exception):
    """An interruption of run_table.py (a kill, in effect) at a chosen point."""


def test_run_table_runs_the_vtnet_row_through_both_stages_and_resumes(
        cli_run, tiny_dir, tmp_path, monkeypatch):
    """experiments/run_table.py, row vtnet, seed 0, cli_run's config (its compiled
    programs): stopped after 4 of the 10 pre-training chunks, a rerun resumes the
    pre-training (the log's samples continue, nothing redone); stopped between the
    stages, a rerun reuses the finished pre-training (api.pretrain not called) and trains
    A2C from it; the results and table.md state the pre-training's budget."""
    import importlib.util

    from orgnav_jax import api
    from orgnav_jax.training import pretrain as P
    path = Path(__file__).parents[1] / "experiments" / "run_table.py"
    spec = importlib.util.spec_from_file_location("run_table", path)
    run_table = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run_table)
    out = tmp_path / "table"
    argv = ["--rows", "vtnet", "--seeds", "0", "--out", str(out), "--scenes-dir", tiny_dir,
            *[a for a in SMALL if a not in ("--quiet", "--no-test")]]
    pre, run = out / "runs" / "vtnet-pretrain-s0", out / "runs" / "vtnet-s0"
    calls = []

    def partial_pretrain(cfg, resume=False, progress=True):
        P.pretrain(cfg, resume=resume, progress=False, stop_after_chunks=4)
        raise _Stop

    def stop(*a, **kw):
        raise _Stop

    monkeypatch.setattr(api, "pretrain", partial_pretrain)
    with pytest.raises(_Stop):
        run_table.main(argv)
    assert [r["samples"] for r in _records(pre, "train")] == [128 * (i + 1) for i in range(4)]
    monkeypatch.setattr(api, "pretrain", lambda cfg, resume=False, progress=True: calls.append(
        resume) or P.pretrain(cfg, resume=resume, progress=False))
    monkeypatch.setattr(api, "train", stop)          # killed before the A2C stage
    with pytest.raises(_Stop):
        run_table.main(argv)
    assert calls == [True] and not run.exists()
    assert [r["samples"] for r in _records(pre, "train")] == [128 * (i + 1) for i in range(10)]
    monkeypatch.undo()
    monkeypatch.setattr(api, "pretrain", stop)       # finished: must not be called again
    run_table.main(argv)
    nav = json.loads((run / "config.json").read_text())
    assert nav["model"] == "vtnet" and nav["pretrained"] == str(pre) and nav["seed"] == 0
    assert (run / "test_results.json").exists()
    got = json.loads((out / "results.json").read_text())["vtnet"]["0"]
    assert got["pretrain_samples"] == 64 * 2 * 10 and got["pretrain_batch"] == 64
    assert got["pretrain_val_accuracy"] == max(r["accuracy"] for r in _records(pre, "val"))
    table = (out / "table.md").read_text()
    assert "| vtnet † | 1 |" in table and "on 1,280 (state, target) samples" in table
    did = [r["did"] for r in json.loads((pre / "provenance.json").read_text())]
    assert did == ["resumed and finished the pre-training (1,280 samples)"]


@pytest.mark.parametrize("argv, message", [
    (["--stage", "pretrain", "--preset", "small"], "config field 'model': 'baseline'"),
    (["--pretrained", "{pre}", "--model", "baseline"], "config field 'pretrained'"),
    (["--pretrained", "{root}/nowhere", "--model", "vtnet"], "not found"),
    (["--pretrained", "{pre}", "--model", "vtnet", "--vtnet-dim", "32"],
     "pre-trained with vtnet_dim 16 (this run: 32)"),
    (["--model", "vtnet", "--vtnet-heads", "5"], "config field 'vtnet_heads': 5"),
    (["--model", "vtnet", "--vtnet-mask", "all"], "config field 'vtnet_mask'"),
])
def test_bad_vtnet_options_are_one_line_before_any_write(cli_run, tiny_dir, cli_error,
                                                        argv, message):
    root, run, _ = cli_run
    fill = {"pre": f"{run}-pretrain", "root": str(root)}
    target = root / "bad"
    argv = [a.format(**fill) for a in argv]
    msg = cli_error(train_cli.main, [*argv, "--scenes-dir", tiny_dir, "--run-dir", target,
                                     "--quiet", "--no-test"])
    assert message in msg
    assert not target.exists()


def test_the_model_and_its_pretraining_build_at_paper_widths(tiny_train):
    """At paper widths the release's counts (d_model 256, 8 heads, FFN 512, 6 + 6 layers,
    LSTM input 49 x 64 + 64 = 3200): shapes only (no arrays made)."""
    cfg = get_config("paper", model="vtnet")
    model = build_model(cfg, tiny_train)
    shapes = jax.eval_shape(lambda: init_params(model, jax.random.PRNGKey(0), tiny_train))
    flat = {_path(p): x.shape for p, x in jax.tree_util.tree_leaves_with_path(shapes)}
    assert flat["params/trunk/lstm_0/input_kernel"] == (3200, 4 * 512)
    assert flat["params/encoder/layer_5/self_attn/kernel"] == (256, 768)
    assert flat["params/trunk/decoder_5/ffn/linear1/kernel"] == (256, 512)
    assert flat["params/encoder/local_1/kernel"] == (256, 249)
    assert flat["params/trunk/rep_0/kernel"] == (256, 128)
    assert "params/encoder/layer_6/norm1/scale" not in flat
