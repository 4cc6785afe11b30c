"""TPN: top-k attention, the release's head (a numpy hand computation, the release's widths),
causal/padding masks, incremental == batched memory, deadlock memory."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax.tpn import deadlock as vd
from orgnav_jax.models import tpn_net as tpn

H = 8
ATOL = 1e-5


def rnd(seed, *shape):
    """Test data from numpy (no per-shape XLA compiles)."""
    return np.random.default_rng(seed).standard_normal(shape).astype(np.float32)


def probs_of(seed, *shape):
    e = np.exp(rnd(seed, *shape, 6))
    return e / e.sum(-1, keepdims=True)


topk = jax.jit(tpn.topk_attention, static_argnums=4)


# ---------------------------------------------------------------------- topk_attention

def test_topk_ignores_padding():
    q, k, v = rnd(0, 5), rnd(1, 7, 5), rnd(2, 7, 3)
    valid = np.array([1, 0, 1, 1, 0, 1, 0], bool)
    out = topk(q, k, v, valid, 3)
    k2 = np.where(valid[:, None], k, 100.0 * q)        # invalid keys now score highest
    v2 = np.where(valid[:, None], v, 1e3)
    np.testing.assert_allclose(topk(q, k2, v2, valid, 3), out, atol=ATOL)
    full = topk(q, k, v, valid, 100)       # k > M: plain masked softmax
    w = np.exp(np.where(valid, k @ q, -np.inf))
    w /= w.sum()
    np.testing.assert_allclose(full, w @ v, atol=ATOL)


def test_topk_no_valid_slot_zero_and_finite_grads():
    q, k, v = rnd(0, 5), rnd(1, 4, 5), rnd(2, 4, 3)
    none = np.zeros(4, bool)
    np.testing.assert_array_equal(topk(q, k, v, none, 2), 0.0)
    grads = jax.grad(lambda q, k, v: tpn.topk_attention(q, k, v, none, 2).sum(),
                     argnums=(0, 1, 2))(q, k, v)
    for g in grads:
        assert np.isfinite(np.asarray(g)).all()
    # one valid slot: its value
    one = none.copy()
    one[2] = True
    np.testing.assert_allclose(topk(q, k, v, one, 3), v[2], atol=ATOL)


def test_topk_selection():
    q = np.array([1.0, 0.0], np.float32)
    k = np.array([[5.0, 0], [3.0, 0], [2.0, 0], [1.0, 0], [9.0, 0]], np.float32)
    v = rnd(3, 5, 4)
    valid = np.array([1, 1, 1, 1, 0], bool)             # slot 4 scores best but is padding
    np.testing.assert_allclose(topk(q, k, v, valid, 1), v[0], atol=ATOL)
    out2 = topk(q, k, v, valid, 2)
    w = np.exp([5.0, 3.0]) / np.exp([5.0, 3.0]).sum()
    np.testing.assert_allclose(out2, w @ v[:2], atol=ATOL)
    k_low = k.copy()
    k_low[2:4, 0] = [2.9, -4.0]    # still ranked below slot 1
    v_low = v.copy()
    v_low[2:4] = 50.0
    np.testing.assert_allclose(topk(q, k_low, v_low, valid, 2), out2, atol=ATOL)
    assert not np.allclose(topk(q, k, v_low, valid, 3), out2, atol=1e-3)


def test_attention_map_spreads_the_read_over_the_slots():
    """The dense map of a top-k read: the same weights as the attended values use, 0 on
    the slots not read and on padding."""
    q, k, v = rnd(7, 3, 8), rnd(8, 3, 12, 8), rnd(9, 3, 12, 5)
    valid = np.arange(12)[None] < np.array([[12], [5], [0]])
    read = tpn.topk_weights(jnp.asarray(q), jnp.asarray(k), jnp.asarray(valid), 4)
    A = np.asarray(tpn.attention_map(read, 12))
    assert A.shape == (3, 12) and np.all(A[~valid] == 0)
    assert np.all((A > 0).sum(1) == [4, 4, 0])
    np.testing.assert_allclose(A.sum(1), [1, 1, 0], atol=ATOL)
    np.testing.assert_allclose(np.einsum("bm,bmv->bv", A, v),
                               topk(q, k, v, valid, 4), atol=ATOL)


def test_topk_leading_dims_match_rows():
    q, k, v = rnd(0, 2, 3, 5), rnd(1, 2, 3, 6, 5), rnd(2, 2, 3, 6, 4)
    valid = np.random.default_rng(4).random((2, 3, 6)) < 0.6
    out = topk(q, k, v, valid, 2)
    for b in range(2):
        for t in range(3):
            np.testing.assert_allclose(
                out[b, t], topk(q[b, t], k[b, t], v[b, t], valid[b, t], 2),
                atol=ATOL)


# ---------------------------------------------------------------------- TPN batched

def randomized(params, seed=30):
    """Every leaf random: kernels N(0, 1/fan_in), biases N(0, 0.3^2), LayerNorm scales
    1 + N(0, 0.3^2) (the init's zero biases and unit scales would hide a missing one)."""
    leaves, tree = jax.tree_util.tree_flatten_with_path(params)
    rng = np.random.default_rng(seed)
    new = []
    for path, x in leaves:
        name = jax.tree_util.keystr(path[-1:])
        z = rng.standard_normal(x.shape).astype(np.float32)
        new.append(z / np.sqrt(x.shape[0]) if "kernel" in name else
                   1 + 0.3 * z if "scale" in name else 0.3 * z)
    return jax.tree_util.tree_unflatten(tree, new)


@pytest.fixture(scope="module")
def model_and_params():
    model = tpn.TPN(hidden=H, action_embed=4, top_k=3)
    B, T = 2, 9
    params = jax.eval_shape(model.init, jax.random.PRNGKey(0), rnd(1, B, T, H),
                            probs_of(2, B, T), np.ones((B, T), bool))
    return model, randomized(params)


@pytest.fixture(scope="module")
def batched(model_and_params):
    model, params = model_and_params
    return jax.jit(lambda h, p, v: model.apply(params, h, p, v))


# the release's head by hand (numpy, float64): models/tpn_net.py's docstring formula
def _ln(x, p):
    mu, var = x.mean(-1, keepdims=True), x.var(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + 1e-5) * p["scale"] + p["bias"]


def _mlp(x, P, a, b, norm=True):
    """Dense a -> (LN) -> ReLU -> Dense b -> (LN)."""
    dense = lambda x, n: x @ P[n]["kernel"] + P[n]["bias"]
    ln = (lambda x, n: _ln(x, P[n])) if norm else (lambda x, n: x)
    x = np.maximum(ln(dense(x, a), a.replace("_", "_norm_")), 0)
    return ln(dense(x, b), b.replace("_", "_norm_"))


def numpy_tpn(P, h, probs, k):
    """One episode, every step valid: h (T, H), probs (T, 6) -> logits (T, 6)."""
    P = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), P["params"])
    relu = lambda x: np.maximum(x, 0)
    r = relu(h + _mlp(h, P, "rep_1", "rep_2"))                         # (T, H)
    e = relu(probs @ P["prob_embed"]["kernel"] + P["prob_embed"]["bias"])
    values = np.concatenate([r[1:], e[:-1]], 1)          # slot i: [r_{i+1}, e_i]
    out = []
    for t in range(len(h)):
        read = np.zeros(values.shape[1])                 # step 0: nothing to read
        if t > 0:
            scores = r[:t] @ r[t]                        # keys r_0 .. r_{t-1}
            top = np.argsort(-scores)[:k]
            w = np.exp(scores[top] - scores[top].max())
            read = (w / w.sum()) @ values[top]
        m = relu(_mlp(read, P, "memory_1", "memory_2"))  # the zero read goes through too
        z = np.concatenate([r[t], m])
        z = relu(z + _mlp(z, P, "block_1", "block_2"))
        out.append(_mlp(z, P, "predict_1", "predict_2", norm=False))
    return np.stack(out)


def test_the_head_is_the_releases_formula(model_and_params, batched):
    """Whole-episode logits against the numpy hand computation of the release's head:
    residual LayerNorm MLPs with their ReLUs, ReLU(Dense(p)) action embedding, the read's
    MLP also at step 0 (zero read), top-k (3 of up to 8 slots) over earlier steps."""
    model, params = model_and_params
    B, T = 2, 9
    h, p = rnd(40, B, T, H), probs_of(41, B, T)
    ours = np.asarray(batched(h, p, np.ones((B, T), bool)))
    for b in range(B):
        ref = numpy_tpn(params, h[b].astype(np.float64), p[b].astype(np.float64), 3)
        np.testing.assert_allclose(ours[b], ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    assert np.ptp(ours[:, 0]) > 0.1        # the zero read at step 0 still gives logits


def test_the_release_widths_and_defaults():
    """At hidden 512 with the default TPN settings the parameters have the release's
    shapes (torch Linear (out, in) = our kernel transposed): 512 -> 256 -> 512, 6 -> 6,
    518 -> 1024 -> 518, 1030 -> 512 -> 1030, 1030 -> 512 -> 6; widths follow hidden."""
    from types import SimpleNamespace
    from orgnav_jax.tpn.config import TPNNetwork
    from orgnav_jax.tpn.test_time import build_tpn, init_tpn_params
    net = build_tpn(SimpleNamespace(hidden=512), TPNNetwork())
    shapes = jax.eval_shape(lambda: init_tpn_params(net, SimpleNamespace(hidden=512),
                                                    jax.random.PRNGKey(0)))["params"]
    dense = {"rep_1": (512, 256), "rep_2": (256, 512), "prob_embed": (6, 6),
             "memory_1": (518, 1024), "memory_2": (1024, 518), "block_1": (1030, 512),
             "block_2": (512, 1030), "predict_1": (1030, 512), "predict_2": (512, 6)}
    norms = {"rep_norm_1": 256, "rep_norm_2": 512, "memory_norm_1": 1024,
             "memory_norm_2": 518, "block_norm_1": 512, "block_norm_2": 1030}
    assert set(shapes) == set(dense) | set(norms)
    for name, (i, o) in dense.items():
        assert shapes[name]["kernel"].shape == (i, o) and shapes[name]["bias"].shape == (o,)
    for name, n in norms.items():
        assert shapes[name]["scale"].shape == shapes[name]["bias"].shape == (n,)
    assert (net.top_k, net.action_embed) == (10, 6)


def test_call_is_causal(batched):
    B, T = 2, 9
    h, p, valid = rnd(5, B, T, H), probs_of(6, B, T), np.ones((B, T), bool)
    out = batched(h, p, valid)
    assert out.shape == (B, T, 6) and np.isfinite(np.asarray(out)).all()
    for t in (0, 3, 7):
        h2, p2 = h.copy(), p.copy()
        h2[:, t + 1:] += rnd(7, B, T - t - 1, H)
        p2[:, t:] = probs_of(8, B, T - t)    # p_t itself is only read later
        np.testing.assert_allclose(batched(h2, p2, valid)[:, :t + 1], out[:, :t + 1],
                                   atol=ATOL)
        # sanity: the past does matter (slot t-1's value p_{t-1} at step t)
        if 0 < t <= 3:                                  # all t slots are in the top 3
            p3 = p.copy()
            p3[:, t - 1] = p[:, t - 1, ::-1]
            assert not np.allclose(batched(h, p3, valid)[:, t], out[:, t], atol=1e-4)


def test_call_ignores_invalid_steps(batched):
    B, T, j = 2, 9, 4
    h, p = rnd(10, B, T, H), probs_of(11, B, T)
    valid = np.ones((B, T), bool)
    valid[:, j] = False
    out = batched(h, p, valid)
    h2, p2 = h.copy(), p.copy()
    h2[:, j] += 5.0
    p2[:, j] = probs_of(12, B)
    other = np.arange(T) != j
    np.testing.assert_allclose(batched(h2, p2, valid)[:, other], out[:, other], atol=ATOL)
    # end-of-episode padding: steps after the end don't change the episode's logits
    ended = np.arange(T)[None] < np.array([[5], [7]])
    out = batched(h, p, ended)
    h3 = np.where(ended[..., None], h, 3.0)
    np.testing.assert_allclose(batched(h3, p, ended)[ended], out[ended], atol=ATOL)


def test_grads_finite_nonzero_every_leaf(model_and_params):
    model, params = model_and_params
    B, T = 2, 9
    h, p = rnd(13, B, T, H), probs_of(14, B, T)
    valid = np.arange(T)[None] < np.array([[9], [6]])
    target = np.random.default_rng(15).integers(0, 6, (B, T))

    def loss(params):
        logp = jax.nn.log_softmax(model.apply(params, h, p, valid))
        ce = -jnp.take_along_axis(logp, target[..., None], -1)[..., 0]
        return jnp.sum(ce * valid) / valid.sum()

    grads = jax.jit(jax.grad(loss))(params)
    for path, g in jax.tree_util.tree_leaves_with_path(grads):
        g = np.asarray(g)
        assert np.isfinite(g).all(), path
        assert np.abs(g).sum() > 0, path


# ---------------------------------------------------------------------- incremental memory

def run_incremental(model, params, h, p, mem, fresh=None):
    """Step through h (B, T, H), p (B, T, 6); fresh (B, T) resets rows -> logits, mem."""
    @jax.jit
    def step(h, p, fresh, mem):
        logits, r, mem, _ = tpn.tpn_step(model, params, h, tpn.memory_reset(mem, fresh))
        return logits, tpn.memory_record(mem, r, p)

    fresh = np.zeros(h.shape[:2], bool) if fresh is None else fresh
    out = []
    for t in range(h.shape[1]):
        logits, mem = step(h[:, t], p[:, t], fresh[:, t], mem)
        out.append(logits)
    return np.stack(out, 1), mem


def test_incremental_equals_batched(model_and_params, batched):
    model, params = model_and_params
    B, T = 2, 9
    h, p = rnd(16, B, T, H), probs_of(17, B, T)
    inc, mem = run_incremental(model, params, h, p, tpn.memory_init(B, 12, H))
    np.testing.assert_allclose(inc, batched(h, p, np.ones((B, T), bool)), atol=ATOL)
    np.testing.assert_array_equal(mem.count, T - 1)
    np.testing.assert_array_equal(tpn.memory_valid(mem).sum(1), T - 1)


def test_reset_makes_episodes_independent(model_and_params, batched):
    model, params = model_and_params
    B, T = 2, 9
    ha, pa = rnd(18, B, 5, H), probs_of(19, B, 5)
    hb, pb = rnd(20, B, T, H), probs_of(21, B, T)
    _, mem = run_incremental(model, params, ha, pa, tpn.memory_init(B, 16, H))
    fresh = np.zeros((B, T), bool)
    fresh[0, 0] = True # only row 0 starts a new episode
    out, _ = run_incremental(model, params, hb, pb, mem, fresh)
    ref = batched(hb, pb, np.ones((B, T), bool))
    np.testing.assert_allclose(out[0], ref[0], atol=ATOL)
    assert not np.allclose(out[1], ref[1], atol=1e-4)   # row 1 still remembers episode A
    both = np.concatenate([ha, hb], 1)[1:], np.concatenate([pa, pb], 1)[1:]
    ref1 = batched(both[0], both[1], np.ones((1, 5 + T), bool))
    np.testing.assert_allclose(out[1], ref1[0, 5:], atol=ATOL)


def test_memory_full_drops_writes(model_and_params, batched):
    model, params = model_and_params
    B, T, M = 2, 9, 3
    h, p = rnd(22, B, T, H), probs_of(23, B, T)
    out, mem = run_incremental(model, params, h, p, tpn.memory_init(B, M, H))
    assert np.isfinite(np.asarray(out)).all()
    np.testing.assert_array_equal(mem.count, M)
    # the first M transitions are kept, so steps <= M match the unbounded memory
    np.testing.assert_allclose(out[:, :M + 1], batched(h, p, np.ones((B, T), bool))[:, :M + 1],
                               atol=ATOL)
    r = jax.jit(lambda h: model.apply(params, h, method=tpn.TPN.represent))(h)
    np.testing.assert_allclose(mem.keys, r[:, :M], atol=ATOL)
    np.testing.assert_allclose(mem.next_r, r[:, 1:M + 1], atol=ATOL)
    np.testing.assert_allclose(mem.probs, p[:, :M], atol=ATOL)


# ---------------------------------------------------------------------- vision deadlock

def test_vision_deadlock_repeat_count_reset():
    B, G, M = 2, 16, 4
    proj = vd.signature_projection(49 * G, 32)
    frames = np.maximum(rnd(24, 6, B, 7, 7, G), 0)
    sig = lambda i: vd.global_signature(frames[i], proj)
    mem = vd.vision_memory_init(B, M, 32)
    deadlock = jax.jit(lambda mem, sig: vd.vision_deadlock(mem, sig, 0.99))
    flags = []
    for i in (0, 1, 2, 1, 0):                           # revisit frame 1, then frame 0
        d, mem = deadlock(mem, sig(i))
        flags.append(np.asarray(d))
    np.testing.assert_array_equal(np.stack(flags), [[0, 0], [0, 0], [0, 0], [1, 1], [1, 1]])
    np.testing.assert_array_equal(mem.count, M)         # full: 5th write dropped, no error
    mem = vd.vision_memory_reset(mem, np.array([True, False]))
    d, mem = deadlock(mem, sig(2))      # stale sigs of row 0 are masked
    np.testing.assert_array_equal(d, [False, True])
    d, _ = deadlock(mem, np.zeros((B, 32), np.float32))
    np.testing.assert_array_equal(d, False)             # zero signature: no NaN, no hit
    assert np.isfinite(np.asarray(mem.sigs)).all()


def test_projection_keeps_cosine_of_near_identical():
    G = 64
    proj = vd.signature_projection(49 * G)
    x = np.maximum(rnd(25, 8, 7, 7, G), 0)
    x2 = x + 0.02 * rnd(26, 8, 7, 7, G)
    y = np.maximum(rnd(27, 8, 7, 7, G), 0)
    cos = jax.jit(lambda a, b: jnp.sum(vd.unit(vd.global_signature(a, proj))
                               * vd.unit(vd.global_signature(b, proj)), -1))
    assert float(cos(x, x2).min()) >= 0.99
    cos_raw = jnp.sum(vd.unit(x.reshape(8, -1)) * vd.unit(y.reshape(8, -1)), -1)
    assert float(jnp.abs(cos(x, y) - cos_raw).mean()) < 0.2   # std ~ (1 - c^2) / sqrt(64)
    assert float(cos(x, y).max()) < 0.9


def test_the_config_parts_default_like_the_flat_config():
    """TPNConfig is the flat surface of its parts: their defaults agree."""
    from orgnav_jax.tpn.config import DeadlockMemory, TestTime, TPNConfig, TPNNetwork
    cfg = TPNConfig()
    assert cfg.network == TPNNetwork() and cfg.memory == DeadlockMemory()
    assert cfg.test_time() == TestTime()
    changed = TPNConfig(tpn_lr=1e-3, deadlock="cosine", top_k=3)
    assert changed.test_time().tpn_lr == 1e-3 and changed.memory.deadlock == "cosine"
    assert changed.network.top_k == 3
    # runs differing in directories, seeds or stage-2 budget share the test-time key
    assert TPNConfig(run_dir="a", seed=3, total_episodes=64).test_time() == TestTime()
