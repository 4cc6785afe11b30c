"""VTNet (Du, Yu, Zheng, ICLR 2021): a visual transformer over the detections, queried by
the cells of the global map, in front of the release's LSTM policy (issue 43).

    model = build_model(get_config("vtnet"), scenes)       # a NavModel (models/navmodel.py)
    pre = VTNetPretrain(model.encoder, model.trunk)          # the pre-training network

Transcribed from the authors' release `xiaobaishu0097/ICLR_VTNet` (models/vtnetmodel.py,
models/transformer.py, models/pretrainedvisualtransformer.py; docs/vtnet.md maps it line
by line). With D = vtnet_dim (the release's d_model 256), R = fuse_channels (its 64):

encoder (VTNetEncoder), the instance tokens and the transformer encoder:
    appearance (B, C, d) -> Dense D ReLU -> Dense D-7 ReLU    (the `fasterrcnn` local
                                                               embedding, 512->256->249)
    token = [that, label c (0..C-1), box / 300 (4), score, target indicator]   (B, C, D)
    -> vtnet_encoder_layers post-norm encoder layers (self-attention, no position term)
trunk (VTNetTrunk), the spatial-aware queries, the decoder and the policy:
    global map (B, 7, 7, G) -> Dense D (the 1x1 conv) ReLU + the fixed sine position
    embedding (position_embedding) -> the queries (B, 49, D)
    decoder: target 0, query position = the queries; vtnet_decoder_layers post-norm layers
    (self-attention, cross-attention to the encoded tokens, FFN), final LayerNorm
    -> one vector per map cell (B, 49, D) -> Dense D/2 ReLU -> Dense R ReLU [dropout]
    previous action (B, 6) -> Dense R ReLU: one more row; [49 rows, action] (B, 50 R)
    -> LSTM x lstm_layers -> actor Dense 6; critic Dense 64 -> Dense 1 (linear)
(the release: 256 -> 128 -> 64 per cell, the action embedding 6 -> 64, LSTM(3200, 512, 2)).

Attention is torch's nn.MultiheadAttention: one in-projection (D, 3D) for q, k, v, scores
q k^T / sqrt(D / heads) per head, softmax, an out-projection; the position term is added to
queries and keys, never to values (DETR's convention, which the release keeps).

Masks (`mask`): the release masks nothing: every category is a token, an undetected one
with zero appearance, box and score (its label and indicator stay), and it attends and is
attended like the others ("none", the default): so the target's token tells the policy
which category it seeks even when nothing of it is detected. "undetected" (a departure,
offered for val) drops the undetected categories other than the target from the keys of
the encoder's self-attention and the decoder's cross-attention (the target's token stays a
key, detected or not; a query with no key left would get a zero attention output, not a
NaN); dropped tokens still get an encoder output, which no decoder query reads.

Mixed precision (dtype bfloat16): matmuls take bf16 operands with float32 accumulation;
the attention scores, their softmax, the LayerNorms and the residual stream stay float32
(a softmax over bf16 scores loses the small differences between keys, and the post-norm
residual sums feed LayerNorm statistics); the LSTM and the heads as in models/trunk.py.

Speed: the decoder's first self-attention reads target 0, so its values are the value
bias alone and its output is out_proj(b_v) for every query whatever the weights, and
norm1 of it one vector: computed so (exact, not an approximation), the first layer skips
its self-attention's scores and a LayerNorm over every cell.
"""

from __future__ import annotations

import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS
from orgnav_jax.errors import choose
from orgnav_jax.models.init import glorot_uniform
from orgnav_jax.models.trunk import LSTMGates, Trunk, cast, compute_dtype, matmul

CELLS = FEATURE_GRID * FEATURE_GRID
LOCATION_ENHANCEMENT = 7      # label, box (4), score, target indicator
LN_EPS = 1e-5                 # torch's LayerNorm epsilon (flax's default is 1e-6)
MASKS = ("none", "undetected")
# parameter paths (under "params") of the pre-trained part: the release's
# PreTrainedVisualTransformer minus its pretrain_fc (main.py loads every name the two
# networks share); the rest (action embedding, LSTM, heads) starts from the release's init
VISUAL_MODULES = ("encoder", "trunk/global_1x1", "trunk/decoder_", "trunk/decoder_norm",
                  "trunk/rep_")


def position_embedding(grid: int = FEATURE_GRID, channels: int = 128) -> np.ndarray:
    """The release's fixed sine embedding of a grid x grid map (get_gloabal_pos_embedding
    (7, 128)) -> (grid * grid, 2 * channels) float32, row r * grid + c for cell (r, c):
    with y = r + 1, x = c + 1 and t_i = 10000 ** (2 * (i // 2) / channels), channel i of
    the first half is sin(y / t_i) for even i and cos(y / t_i) for odd i; the second half
    the same of x."""
    if channels % 2:
        raise ValueError(f"position embedding: channels must be even, got {channels}")
    i = np.arange(channels, dtype=np.float64)
    t = 10000.0 ** (2 * (i // 2) / channels)
    coord = np.arange(1, grid + 1, dtype=np.float64)[:, None] / t        # (grid, channels)
    wave = np.where(i % 2 == 0, np.sin(coord), np.cos(coord))
    y = np.repeat(wave, grid, axis=0)          # cell r * grid + c -> row r
    x = np.tile(wave, (grid, 1))               # -> column c
    return np.concatenate([y, x], axis=1).astype(np.float32)


def attention_weights(q, k, keep=None):
    """Softmax attention weights in float32: q (B, H, Lq, Dh), k (B, H, Lk, Dh) (any
    dtype; the products accumulate in float32), keep (B, Lk) bool or None -> (B, H, Lq, Lk)
    float32. Keys where keep is False get weight 0; a query with no key kept gets all
    weights 0 (its attention output is then 0, where a plain masked softmax gives NaN)."""
    scale = 1.0 / math.sqrt(q.shape[-1])
    s = jnp.matmul(q, jnp.swapaxes(k, -1, -2), preferred_element_type=jnp.float32) * scale
    if keep is None:
        return jax.nn.softmax(s, axis=-1)
    kept = keep[:, None, None, :]
    s = jnp.where(kept, s, -jnp.inf)
    m = jnp.max(s, axis=-1, keepdims=True)
    e = jnp.where(kept, jnp.exp(s - jnp.where(jnp.isfinite(m), m, 0.0)), 0.0)
    return e / jnp.maximum(e.sum(-1, keepdims=True), jnp.finfo(jnp.float32).tiny)


def split_heads(x, heads: int):
    """(B, L, D) -> (B, H, L, D / H): batch dimensions leading, the layout XLA's CPU
    batched matmul runs fastest (einsum over (B, L, H, Dh) was ~2x slower here)."""
    B, L, D = x.shape
    return jnp.swapaxes(x.reshape(B, L, heads, D // heads), 1, 2)


class MultiheadAttention(nn.Module):
    """torch's nn.MultiheadAttention (batch first): params `kernel` (D, 3D) and `bias` (3D,)
    of the in-projection (q, k, v column blocks), `out_proj`."""
    dim: int
    heads: int
    dtype: Any = None

    def setup(self):
        D = self.dim
        self.kernel = self.param("kernel", nn.initializers.lecun_normal(), (D, 3 * D))
        self.bias = self.param("bias", nn.initializers.zeros, (3 * D,))
        self.out_proj = nn.Dense(D, dtype=self.dtype)

    def __call__(self, q_in, k_in, v_in, keep=None):
        D, H, w, b = self.dim, self.heads, self.kernel, self.bias
        B, Lq = q_in.shape[0], q_in.shape[1]
        # inputs shared between q, k, v take one matmul (fewer, larger matmuls: CPU)
        if q_in is k_in and k_in is v_in:
            q, k, v = jnp.split(matmul(q_in, w, self.dtype) + b, 3, axis=-1)
        elif q_in is k_in:
            q, k = jnp.split(matmul(q_in, w[:, :2 * D], self.dtype) + b[:2 * D], 2, axis=-1)
            v = matmul(v_in, w[:, 2 * D:], self.dtype) + b[2 * D:]
        else:
            q = matmul(q_in, w[:, :D], self.dtype) + b[:D]
            if k_in is v_in:
                k, v = jnp.split(matmul(k_in, w[:, D:], self.dtype) + b[D:], 2, axis=-1)
            else:
                k = matmul(k_in, w[:, D:2 * D], self.dtype) + b[D:2 * D]
                v = matmul(v_in, w[:, 2 * D:], self.dtype) + b[2 * D:]
        heads = lambda x: split_heads(cast(x, self.dtype), H)
        a = attention_weights(heads(q), heads(k), keep)
        out = jnp.matmul(cast(a, self.dtype), heads(v), preferred_element_type=jnp.float32)
        return self.out_proj(jnp.swapaxes(out, 1, 2).reshape(B, Lq, D))

    def constant_output(self):
        """The output for values that are all 0 (the decoder's first self-attention):
        the weights sum to 1, so every query gets out_proj(b_v), whatever q and k -> (D,)."""
        return self.out_proj(self.bias[2 * self.dim:])


class FeedForward(nn.Module):
    """linear2(ReLU(linear1(x))): D -> ffn -> D."""
    dim: int
    ffn: int
    dtype: Any = None

    @nn.compact
    def __call__(self, x):
        h = nn.relu(nn.Dense(self.ffn, name="linear1", dtype=self.dtype)(x))
        return nn.Dense(self.dim, name="linear2", dtype=self.dtype)(h)


def _norm(name: str) -> nn.LayerNorm:
    return nn.LayerNorm(epsilon=LN_EPS, name=name, dtype=jnp.float32)


class EncoderLayer(nn.Module):
    """The release's TransformerEncoderLayer.forward_post with no position term:
    x = norm1(x + self_attn(x, x, x)); x = norm2(x + ffn(x))."""
    dim: int
    heads: int
    ffn: int
    dtype: Any = None

    @nn.compact
    def __call__(self, x, keep=None):
        a = MultiheadAttention(self.dim, self.heads, self.dtype, name="self_attn")(x, x, x, keep)
        x = _norm("norm1")(x + a.astype(jnp.float32))
        f = FeedForward(self.dim, self.ffn, self.dtype, name="ffn")(x)
        return _norm("norm2")(x + f.astype(jnp.float32))


class DecoderLayer(nn.Module):
    """The release's TransformerDecoderLayer.forward_post (memory without a position term):
    t = norm1(t + self_attn(t + p, t + p, t)); t = norm2(t + cross_attn(t + p, m, m));
    t = norm3(t + ffn(t)). `first`: t is 0 (module docstring: the constant output)."""
    dim: int
    heads: int
    ffn: int
    dtype: Any = None

    @nn.compact
    def __call__(self, t, memory, query_pos, keep=None, first: bool = False):
        attn = MultiheadAttention(self.dim, self.heads, self.dtype, name="self_attn")
        if first:      # t = 0: norm1(0 + out_proj(b_v)) is one vector for every query
            t = jnp.broadcast_to(_norm("norm1")(attn.constant_output().astype(jnp.float32)),
                                 query_pos.shape)
        else:
            q = t + query_pos
            t = _norm("norm1")(t + attn(q, q, t).astype(jnp.float32))
        c = MultiheadAttention(self.dim, self.heads, self.dtype, name="cross_attn")(
            t + query_pos, memory, memory, keep)
        t = _norm("norm2")(t + c.astype(jnp.float32))
        f = FeedForward(self.dim, self.ffn, self.dtype, name="ffn")(t)
        return _norm("norm3")(t + f.astype(jnp.float32))


def kept_keys(conf, target, mask: str):
    """The keys the attention masks keep (module docstring): None (mask "none", the
    release) or (B, C) bool, the detected categories and the target (mask "undetected")."""
    return choose({"none": lambda: None, "undetected": lambda: (conf > 0) | (target > 0)},
                  mask, "VTNet attention mask (vtnet_mask)")()


class VTNetEncoder(nn.Module):
    """Instance tokens and the transformer encoder (module docstring) -> (encoded tokens
    (B, C, dim) float32, the kept keys (B, C) bool or None): the trunk's decoder reads
    both (NavModel passes an encoder's second output to the trunk as `extra`)."""
    dim: int = 16
    heads: int = 1
    ffn: int = 32
    layers: int = 1
    mask: str = "none"
    dtype: Any = None

    @nn.nowrap
    def build_trunk(self, cfg) -> "VTNetTrunk":
        """The trunk this encoder works with (models/navmodel.py: build_model)."""
        return VTNetTrunk(dim=self.dim, heads=self.heads, ffn=self.ffn,
                          decoder_layers=cfg.vtnet_decoder_layers,
                          fuse_channels=cfg.fuse_channels, action_embed=cfg.fuse_channels,
                          hidden=cfg.hidden, lstm_layers=cfg.lstm_layers,
                          dtype=compute_dtype(cfg), form=cfg.net)

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        dt = self.dtype
        h = nn.relu(nn.Dense(self.dim, name="local_0", dtype=dt)(app))
        h = nn.relu(nn.Dense(self.dim - LOCATION_ENHANCEMENT, name="local_1", dtype=dt)(h))
        label = jnp.broadcast_to(jnp.arange(app.shape[-2], dtype=jnp.float32)[:, None],
                                 conf.shape + (1,))
        x = jnp.concatenate([h.astype(jnp.float32), label, box, conf[..., None],
                             target[..., None]], axis=-1)
        keep = kept_keys(conf, target, self.mask)
        for i in range(self.layers):
            x = EncoderLayer(self.dim, self.heads, self.ffn, dt, name=f"layer_{i}")(x, keep)
        return x, keep


class VTNetTrunk(Trunk):
    """The queries, the decoder, the per-cell embedding and the release's LSTM policy
    (module docstring). `fuse_channels` is R (the per-cell width, the release's 64) and
    `action_embed` the previous action's row (the release's 64 = R). recur, the heads,
    initial_carry and the release form come from Trunk; dropout (the release's
    visual_rep_embedding Dropout) masks the R per-cell channels."""
    dim: int = 16
    heads: int = 1
    ffn: int = 32
    decoder_layers: int = 1

    def setup(self):
        R = self.fuse_channels
        self.global_1x1 = nn.Dense(self.dim, dtype=self.dtype)
        self.decoder = [DecoderLayer(self.dim, self.heads, self.ffn, self.dtype)
                        for _ in range(self.decoder_layers)]
        self.decoder_norm = _norm("decoder_norm")
        self.rep_0 = nn.Dense(self.dim // 2, dtype=self.dtype)
        self.rep_1 = nn.Dense(R, dtype=self.dtype)
        self.action_dense = nn.Dense(self.action_embed, dtype=self.dtype)
        flat = CELLS * R + self.action_embed
        self.lstm = [LSTMGates(self.hidden, flat if i == 0 else self.hidden, self.dtype)
                     for i in range(self.lstm_layers)]
        self.actor = nn.Dense(NUM_ACTIONS)
        self.critic_hidden = nn.Dense(64)
        self.critic = nn.Dense(1)

    def dropout_channels(self) -> int:
        return self.fuse_channels

    def queries(self, glob):
        """(B, 7, 7, G) -> the spatial-aware queries (B, 49, dim) float32."""
        g = nn.relu(self.global_1x1(glob)).astype(jnp.float32)
        pos = jnp.asarray(position_embedding(FEATURE_GRID, self.dim // 2))
        return g.reshape(g.shape[0], CELLS, self.dim) + pos

    def decode(self, glob, tokens, keep=None):
        """The decoder's output, one vector per map cell -> (B, 49, dim) float32."""
        query_pos = self.queries(glob)
        t = jnp.zeros_like(query_pos)
        for i, layer in enumerate(self.decoder):
            t = layer(t, tokens, query_pos, keep, first=i == 0)
        return self.decoder_norm(t)

    def visual(self, glob, tokens, keep=None, drop=None):
        """-> the per-cell representation (B, 49, R): decode, then 256 -> 128 -> 64."""
        r = nn.relu(self.rep_1(nn.relu(self.rep_0(self.decode(glob, tokens, keep)))))
        if drop is not None:
            r = r * cast(drop, self.dtype).reshape(r.shape)
        return r

    def embed(self, glob, cat_maps, prev_action, drop=None, extra=None):
        """(B, 7, 7, G), encoded tokens (B, C, dim), (B, 6), dropout mask (B, 7, 7, R) or
        None, kept keys (B, C) or None -> first-layer LSTM input gates (B, 4 hidden)."""
        r = self.visual(glob, cat_maps, extra, drop)
        a = nn.relu(self.action_dense(prev_action))
        x = jnp.concatenate([r.reshape(r.shape[0], -1), cast(a, self.dtype)], axis=-1)
        return self.lstm[0].project(x)


class VTNetPretrain(nn.Module):
    """The release's PreTrainedVisualTransformer: the encoder, the trunk's visual part and
    `pretrain_fc` (49 R -> 6) -> action logits (B, 6). Its parameters carry the navigation
    model's names (encoder/..., trunk/...), so the A2C stage starts from them by name
    (VISUAL_MODULES; training/pretrain.py)."""
    encoder: VTNetEncoder
    trunk: VTNetTrunk

    @nn.compact
    def __call__(self, inputs, train: bool = False):
        tokens, keep = self.encoder(inputs.app, inputs.box, inputs.conf, inputs.target, train)
        r = self.trunk.visual(inputs.glob, tokens, keep, inputs.drop)
        return nn.Dense(NUM_ACTIONS, name="pretrain_fc")(r.reshape(r.shape[0], -1)
                                                         .astype(jnp.float32))


def is_visual(path: str) -> bool:
    """Whether a parameter path ('encoder/layer_0/...', 'trunk/lstm_0/...') belongs to the
    pre-trained part (VISUAL_MODULES)."""
    return any(path.startswith(p) for p in VISUAL_MODULES)


def visual_mask(params):
    """A bool tree shaped like a VTNet's variables: True on the pre-trained leaves (for the
    optimiser's pretrained_lr_scale: training/update.py)."""
    def visual(path, _):
        names = [str(getattr(p, "key", getattr(p, "name", p))) for p in path]
        return is_visual("/".join(names[1:] if names[:1] == ["params"] else names))
    return jax.tree_util.tree_map_with_path(visual, params)


def step_floats(cfg, num_categories: int) -> int:
    """float32 activations per env step of VTNet's embed (forward), for the memory estimate
    (training/memory.py): per layer the residual stream, q, k, v, the attention output,
    the FFN's hidden layer and its mask, the norms' inputs and statistics and the
    (heads x L x L') scores and weights; calibrated above XLA's scratch of the compiled
    chunk (paper widths, N 16, T 16: 3.2 GB, the estimate's activations 4.2 GB)."""
    C, D, F, H = num_categories, cfg.vtnet_dim, cfg.vtnet_ffn, cfg.vtnet_heads
    enc = cfg.vtnet_encoder_layers * (C * (16 * D + 3 * F) + 4 * H * C * C)
    dec = cfg.vtnet_decoder_layers * (CELLS * (24 * D + 3 * F) + 4 * H * CELLS * (CELLS + C))
    head = CELLS * (2 * D + D // 2 + cfg.fuse_channels) + cfg.fuse_channels
    return C * 2 * D + enc + dec + head


def pretrain_init(params, key: jax.Array):
    """The release's pre-training network's initial values (PreTrainedVisualTransformer
    calls no weights_init): torch's defaults, U(+-1/sqrt(fan_in)) for the kernels and
    biases of every Linear and Conv, except inside the transformer, whose 2-D weights
    Transformer._reset_parameters redraws Glorot uniform and whose attention biases
    nn.MultiheadAttention zeroes (its FFN biases keep torch's default); LayerNorm (1, 0).
    Shapes and dtypes unchanged, deterministic in `key`."""
    leaves, treedef = jax.tree_util.tree_flatten_with_path(params)
    keys = jax.random.split(key, max(len(leaves), 1))
    out = []
    for (path, x), k in zip(leaves, keys):
        name = [str(getattr(p, "key", getattr(p, "name", p))) for p in path]
        in_transformer = any(n.startswith(("layer_", "decoder_")) and n != "decoder_norm"
                             for n in name)
        in_attention = any(n in ("self_attn", "cross_attn") for n in name)
        leaf = name[-1]
        if leaf == "kernel" and x.ndim == 2:
            if in_transformer:
                x = glorot_uniform(k, x.shape)
            else:
                bound = 1.0 / math.sqrt(x.shape[0])
                x = jax.random.uniform(k, x.shape, x.dtype, -bound, bound)
        elif leaf == "bias" and "norm" not in name[-2]:
            if in_attention:
                x = jnp.zeros_like(x)
            else:   # torch's default bias: U(+-1/sqrt(fan_in)), fan_in from the kernel
                fan_in = _fan_in(params, path)
                bound = 1.0 / math.sqrt(fan_in)
                x = jax.random.uniform(k, x.shape, x.dtype, -bound, bound)
        out.append(x)
    return jax.tree_util.tree_unflatten(treedef, out)


def _fan_in(params, bias_path) -> int:
    """The input width of the layer a bias belongs to (its sibling kernel's rows)."""
    node = params
    for p in bias_path[:-1]:
        node = node[getattr(p, "key", getattr(p, "name", p))]
    return int(node["kernel"].shape[0])
