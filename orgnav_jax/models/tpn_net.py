"""Tentative Policy Network (paper Sec. 3.4) and its internal state memory: the release's
head (xiaobaishu0097/ECCV-VN, models/metamemorygraphmodel.py), every width derived from
the LSTM width H as the release's at H = 512; E = action_embed (the release's 6), A = 6
actions. LN: LayerNorm (epsilon 1e-5, torch's); Dense_n: a Dense layer to n units.

    h_t (H,)      LSTM output
    r_t (H,)      = ReLU(h_t + LN(Dense_H(ReLU(LN(Dense_{H//2}(h_t))))))     state rep
    e_i (E,)      = ReLU(Dense_E(p_i))             p_i (6,): the base policy's probs at i
    slot i        : key r_i, value [r_{i+1}, e_i] (H+E,)
    read_t (H+E,) = top-k softmax attention of r_t over the complete slots i <= t-1;
                    zeros when there is none (step 0)
    m_t (H+E,)    = ReLU(LN(Dense_{H+E}(ReLU(LN(Dense_{2H}(read_t))))))    (also at step 0)
    z_t (2H+E,)   = [r_t, m_t];  z_t <- ReLU(z_t + LN(Dense_{2H+E}(ReLU(LN(Dense_H(z_t))))))
    logits_t (A,) = Dense_A(ReLU(Dense_H(z_t)))

At H = 512, E = 6: 512 -> 256 -> 512, 6 -> 6, 518 -> 1024 -> 518, 1030 -> 512 -> 1030,
1030 -> 512 -> 6, the release's. Dense kernels start Glorot-uniform, biases 0 (the
release's weights_init). Parameters (flax names; the release's state_dict names in
docs/tpn.md): rep_1, rep_norm_1, rep_2, rep_norm_2; prob_embed; memory_1, memory_norm_1,
memory_2, memory_norm_2; block_1, block_norm_1, block_2, block_norm_2; predict_1, predict_2.

TPN.__call__ reads whole episodes (B, T, .) at once with a (T, T) causal mask (training);
TPNMemory + memory_* functions + TPN.step_logits run it step by step (test time) and give
the same logits. Slots >= t (the future) and padding are never read.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from orgnav_jax.constants import NUM_ACTIONS


def masked_softmax(scores: jax.Array, mask: jax.Array) -> jax.Array:
    """(..., K) scores, (..., K) bool -> (..., K) weights; 0 where masked, all 0 when no entry
    is valid. NaN-free in value and gradient (max over valid entries only, stop-gradient)."""
    m = jnp.max(jnp.where(mask, scores, -jnp.inf), axis=-1, keepdims=True)
    m = jax.lax.stop_gradient(jnp.where(jnp.isfinite(m), m, 0.0))
    e = jnp.where(mask, jnp.exp(jnp.where(mask, scores, m) - m), 0.0)
    denom = jnp.sum(e, axis=-1, keepdims=True)
    return e / jnp.where(denom > 0, denom, 1.0)


def topk_weights(query, keys, valid, k: int):
    """query (..., D), keys (..., M, D), valid (..., M) -> (weights (..., k'), index
    (..., k')), k' = min(k, M): the k highest valid dot-product scores, softmaxed (invalid
    ones among them weigh 0). Leading dims broadcast."""
    scores = jnp.einsum("...d,...md->...m", query, keys)
    scores, valid = jnp.broadcast_arrays(scores, valid)
    _, idx = jax.lax.top_k(jnp.where(valid, scores, -jnp.inf), min(k, keys.shape[-2]))
    w = masked_softmax(jnp.take_along_axis(scores, idx, -1), jnp.take_along_axis(valid, idx, -1))
    return w, idx


def topk_attention(query, keys, values, valid, k: int) -> jax.Array:
    """query (..., D), keys (..., M, D), values (..., M, V), valid (..., M) -> (..., V).

    Dot-product scores; the k (clipped to M) highest valid scores are softmaxed, the rest
    get weight 0; zeros when no slot is valid. Leading dims broadcast (e.g. queries
    (B, T, D) against keys (B, 1, M, D) with valid (B, T, M)) and nothing is tiled."""
    if keys.shape[-2] == 0:
        return jnp.zeros(jnp.broadcast_shapes(query.shape[:-1], valid.shape[:-1])
                         + values.shape[-1:], values.dtype)
    w, idx = topk_weights(query, keys, valid, k)
    values = values.reshape((1,) * (idx.ndim + 1 - values.ndim) + values.shape)
    picked = jnp.take_along_axis(values, idx[..., None], axis=-2)         # (..., k, V)
    return jnp.einsum("...k,...kv->...v", w, picked)


class TPN(nn.Module):
    """Tentative policy network over LSTM outputs of width `hidden` (the module docstring:
    the formula, widths and parameter names)."""
    hidden: int
    action_embed: int = 6
    top_k: int = 10

    def setup(self):
        H, E = self.hidden, self.action_embed
        dense = lambda n: nn.Dense(n, kernel_init=nn.initializers.xavier_uniform())
        norm = lambda: nn.LayerNorm(epsilon=1e-5)
        self.rep_1, self.rep_norm_1 = dense(max(1, H // 2)), norm()
        self.rep_2, self.rep_norm_2 = dense(H), norm()
        self.prob_embed = dense(E)
        self.memory_1, self.memory_norm_1 = dense(2 * H), norm()
        self.memory_2, self.memory_norm_2 = dense(H + E), norm()
        self.block_1, self.block_norm_1 = dense(H), norm()
        self.block_2, self.block_norm_2 = dense(2 * H + E), norm()
        self.predict_1, self.predict_2 = dense(H), dense(NUM_ACTIONS)

    def represent(self, h):
        """(..., H) LSTM output -> r (..., H): ReLU(h + LN(Dense(ReLU(LN(Dense(h))))))."""
        x = nn.relu(self.rep_norm_1(self.rep_1(h)))
        return nn.relu(h + self.rep_norm_2(self.rep_2(x)))

    def embed_probs(self, probs):
        """(..., 6) policy probabilities -> (..., E): ReLU(Dense(p)). (The release embeds
        them when it writes a slot; the TPN's parameters are fixed within an episode, so
        embedding at read time is the same.)"""
        return nn.relu(self.prob_embed(probs))

    def _head(self, r, read):
        """r (..., H), read (..., H+E) (zeros: nothing read) -> logits (..., 6)."""
        m = nn.relu(self.memory_norm_1(self.memory_1(read)))
        m = nn.relu(self.memory_norm_2(self.memory_2(m)))
        z = jnp.concatenate([r, m], axis=-1)
        res = nn.relu(self.block_norm_1(self.block_1(z)))
        z = nn.relu(z + self.block_norm_2(self.block_2(res)))
        return self.predict_2(nn.relu(self.predict_1(z)))

    def read_logits(self, r, keys, next_r, probs, valid):
        """r (B, H), keys (B, M, H), next_r (B, M, H), probs (B, M, 6), valid (B, M)
        -> (logits (B, 6), read = (weights (B, k), slots (B, k)): the top-k slots read and
        their weights). Values are gathered for the top-k slots only (the same read as
        topk_attention over all M values, without materializing them)."""
        w, idx = topk_weights(r, keys, valid, self.top_k)                  # (B, k)
        pick = lambda buf: jnp.take_along_axis(buf, idx[..., None], axis=-2)
        values = jnp.concatenate([pick(next_r), self.embed_probs(pick(probs))], axis=-1)
        return self._head(r, jnp.einsum("bk,bkv->bv", w, values)), (w, idx)

    def __call__(self, h, probs, valid):
        """Whole episodes: h (B, T, H), probs (B, T, 6), valid (B, T) -> logits (B, T, 6).
        Step t reads slots i <= t-1 with valid[i] & valid[i+1]: key r_i, value (r_{i+1}, e_i).
        Slot T-1 has no successor and is never read."""
        T = h.shape[1]
        r = self.represent(h)                                            # (B, T, H)
        next_r = jnp.concatenate([r[:, 1:], jnp.zeros_like(r[:, :1])], axis=1)
        slot_ok = valid & jnp.concatenate([valid[:, 1:], jnp.zeros_like(valid[:, :1])], 1)
        causal = jnp.tril(jnp.ones((T, T), bool), k=-1)                  # [t, i]: i < t
        mask = causal[None] & slot_ok[:, None, :]                        # (B, T, T)
        values = jnp.concatenate([next_r, self.embed_probs(probs)], axis=-1)
        read = topk_attention(r, r[:, None], values[:, None], mask, self.top_k)
        return self._head(r, read)

    def step_logits(self, h, mem: "TPNMemory"):
        """One test-time step: h (B, H) -> (logits (B, 6), r (B, H), mem with the slot that
        r completes, read: the top-k slots read and their weights, see read_logits;
        attention_map spreads it over the memory, i.e. over the episode's earlier steps:
        the paper's Fig. 3 left). Afterwards call memory_record(mem, r, policy probs)."""
        r = self.represent(h)
        mem = memory_observe(mem, r)
        logits, read = self.read_logits(r, mem.keys, mem.next_r, mem.probs, memory_valid(mem))
        return logits, r, mem, read


def step_floats(hidden: int, action_embed: int, top_k: int) -> int:
    """Floats of the TPN's forward activations for one step of TPN.__call__ (each layer's
    output, its LayerNorm and ReLU; the values and the top-k read), for memory estimates."""
    H, E, A = hidden, action_embed, NUM_ACTIONS
    return (3 * max(1, H // 2) + 3 * H             # represent
            + 2 * E + (H + E) + top_k * (H + E)    # values, the top-k slots read
            + 3 * 2 * H + 3 * (H + E)              # the read's MLP
            + (2 * H + E) + 3 * H + 3 * (2 * H + E)  # z, the residual block
            + 2 * H + A)                            # predict


def attention_map(read, size: int) -> jax.Array:
    """read = (weights (B, k), slots (B, k)) -> (B, size): each slot's weight, 0 for the
    slots not read."""
    w, idx = read
    return jnp.zeros((w.shape[0], size), w.dtype).at[jnp.arange(w.shape[0])[:, None], idx].add(w)


@struct.dataclass
class TPNMemory:
    """Per-env internal memory. keys/next_r (B, M, H), probs (B, M, 6): slots 0..count-1 are
    complete (r_i, r_{i+1}, p_i); prev_r (B, H), prev_probs (B, 6): the last step acted on
    (its slot waits for the next r); has_prev (B,) bool; count (B,) int32."""
    keys: jax.Array
    next_r: jax.Array
    probs: jax.Array
    count: jax.Array
    prev_r: jax.Array
    prev_probs: jax.Array
    has_prev: jax.Array


def memory_init(batch: int, size: int, hidden: int) -> TPNMemory:
    """Empty memory of `size` slots per env."""
    z = jnp.zeros
    return TPNMemory(keys=z((batch, size, hidden)), next_r=z((batch, size, hidden)),
                     probs=z((batch, size, NUM_ACTIONS)), count=z((batch,), jnp.int32),
                     prev_r=z((batch, hidden)), prev_probs=z((batch, NUM_ACTIONS)),
                     has_prev=z((batch,), bool))


def memory_reset(mem: TPNMemory, fresh: jax.Array) -> TPNMemory:
    """fresh (B,) bool: those rows forget their episode (count 0, no pending step); stale
    buffer contents stay but are masked by count."""
    return mem.replace(count=jnp.where(fresh, 0, mem.count), has_prev=mem.has_prev & ~fresh)


def memory_observe(mem: TPNMemory, r: jax.Array) -> TPNMemory:
    """r (B, H) = r_t: rows with a pending step write slot `count` = (prev_r, r_t, prev_probs)
    and count += 1. When the buffer is full (count == M) the write is silently dropped: the
    memory keeps the episode's first M transitions."""
    B, M = mem.keys.shape[:2]
    write = mem.has_prev & (mem.count < M)
    rows, slot = jnp.arange(B), jnp.where(write, mem.count, M)            # M: out of range
    put = lambda buf, x: buf.at[rows, slot].set(x, mode="drop")
    return mem.replace(keys=put(mem.keys, mem.prev_r), next_r=put(mem.next_r, r),
                       probs=put(mem.probs, mem.prev_probs), count=mem.count + write)


def memory_record(mem: TPNMemory, r: jax.Array, probs: jax.Array) -> TPNMemory:
    """After the policy acted at step t: r (B, H) = r_t, probs (B, 6) = p_t become pending."""
    return mem.replace(prev_r=r, prev_probs=probs, has_prev=jnp.ones_like(mem.has_prev))


def memory_valid(mem: TPNMemory) -> jax.Array:
    """(B, M) bool: slot index < count."""
    return jnp.arange(mem.keys.shape[1])[None, :] < mem.count[:, None]


def tpn_step(model: TPN, params, h: jax.Array, mem: TPNMemory):
    """Pure form of TPN.step_logits: -> (logits (B, 6), r (B, H), mem, read)."""
    return model.apply(params, h, mem, method=TPN.step_logits)
