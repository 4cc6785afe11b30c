"""The navigation trunk shared by every model, as the authors' release computes it.

global map (B, 7, 7, G)  -> Dense(glob_channels) ReLU [dropout]
previous action (B, 6)   -> Dense(action_embed) ReLU, tiled to 7x7
category maps (B, C, 49) -> ReLU, 7x7xC
concat -> Dense(fuse_channels) ReLU [dropout] -> flatten (B, 49*fuse)
  [+ an encoder's extra vector (B, extra_features) concatenated: D-SP's graph branch]
-> LSTM x layers
-> actor Dense(6) logits; critic Dense(64) Dense(1) (linear: no ReLU between).
(release `models/basemodel.py:66-95`; the previous action is the previous step's action
probabilities, models/navmodel.py.) 1x1 convolutions are written as Dense over channels
(much faster on CPU under scan). `form="pre_parity"` is the trunk this project used
before issue 39 (no ReLU on the category maps or the action embedding, a ReLU inside
the critic, one dropout site): runs of config version <= 6 were trained with it and keep
it (docs/training.md).

The trunk is split in two so that training can batch the non-recurrent part over time:
`embed` maps one step's inputs to the first LSTM layer's input gates (B, 4*hidden) and
does not depend on earlier steps; `recur` runs the recurrence and the heads. In the loss
`embed` runs once over all T*N steps of a rollout (large matmuls) and only `recur` is
scanned. `recur` is `lstm_step` (the LSTM layers) then `actor_critic` (the heads);
SAVN's segments scan `lstm_step` alone and run the heads once after the scan
(training/savn.py). The LSTM cell is flax's (gates i, f, g, o; input kernels
lecun-normal, recurrent kernels orthogonal per gate, zero bias), with its input
projection done in `embed`.

Mixed precision (`dtype=jnp.bfloat16`, TrainConfig.dtype): the layers up to the LSTM
compute in bf16 (flax's `dtype`; parameters stay float32, flax's `param_dtype`); the LSTM
matmuls take bf16 operands and accumulate in float32 (`preferred_element_type`), the
gates, the cell state and the carry stay float32, and the actor and critic heads run in
float32 (their softmax and value regression want the precision; they are tiny). With
dtype None (float32) the program is the plain float32 one.

Dropout (the release's 0.25, element-wise, after the global map's 1x1 layer and again
after the fusion 1x1 layer) is an explicit mask input, not flax's rng-driven nn.Dropout:
one mask (B, 7, 7, glob_channels + fuse_channels) holds both sites' masks (the
pre-parity form reads only the first glob_channels); the rollout draws the mask of each
step from a key it stores in the trajectory, and the loss's replay rebuilds the very
same masks (`dropout_mask`). Without a mask (evaluation) the trunk is deterministic.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from typing import Any

from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS
from orgnav_jax.errors import choose


def compute_dtype(cfg):
    """The modules' compute dtype for a config's `dtype` field: None (float32 as it is)
    or jnp.bfloat16 (mixed precision, float32 parameters; see above)."""
    return {"float32": None, "bfloat16": jnp.bfloat16}[getattr(cfg, "dtype", "float32")]


def cast(x, dtype):
    """x in the compute dtype (unchanged when dtype is None: float32 as it is)."""
    return x if dtype is None else x.astype(dtype)


def matmul(x, kernel, dtype):
    """x @ kernel; in `dtype` operands with float32 accumulation and result if given."""
    if dtype is None:
        return x @ kernel
    return jnp.dot(x.astype(dtype), kernel.astype(dtype),
                   preferred_element_type=jnp.float32)


def _per_gate(init):
    """An initializer for a (in, 4*H) kernel: `init` applied to each (in, H) gate block."""
    def init_fn(key, shape, dtype=jnp.float32):
        rows, cols = shape
        keys = jax.random.split(key, 4)
        return jnp.concatenate([init(k, (rows, cols // 4), dtype) for k in keys], axis=-1)
    return init_fn


class LSTMGates(nn.Module):
    """An LSTM layer with its input projection apart: `project(x)` (B, in) -> (B, 4H) input
    gates; `recur(gates, (c, h))` -> ((c, h), h), each (B, H)."""
    features: int
    in_features: int
    dtype: Any = None          # compute dtype of the matmuls (None: float32)

    def setup(self):
        H = self.features
        self.input_kernel = self.param("input_kernel", _per_gate(nn.initializers.lecun_normal()),
                                       (self.in_features, 4 * H))
        self.recurrent_kernel = self.param("recurrent_kernel",
                                           _per_gate(nn.initializers.orthogonal()), (H, 4 * H))
        self.bias = self.param("bias", nn.initializers.zeros, (4 * H,))

    def project(self, x):
        return matmul(x, self.input_kernel, self.dtype) + self.bias

    def recur(self, gates, carry):
        c, h = carry
        gi, gf, gg, go = jnp.split(gates + matmul(h, self.recurrent_kernel, self.dtype), 4,
                                   axis=-1)
        c = nn.sigmoid(gf) * c + nn.sigmoid(gi) * jnp.tanh(gg)
        h = nn.sigmoid(go) * jnp.tanh(c)
        return (c, h), h


class Trunk(nn.Module):
    glob_channels: int = 64
    action_embed: int = 10
    fuse_channels: int = 64
    hidden: int = 512
    lstm_layers: int = 2
    dtype: Any = None          # compute dtype below the heads (None: float32)
    form: str = "release"      # "release" | "pre_parity" (module docstring)
    extra_features: int = 0    # width of a vector concatenated to the flattened LSTM
                               # input (an encoder's second output; 0: none)

    def setup(self):
        self.global_1x1 = nn.Dense(self.glob_channels, dtype=self.dtype)
        self.action_dense = nn.Dense(self.action_embed, dtype=self.dtype)
        self.fuse_1x1 = nn.Dense(self.fuse_channels, dtype=self.dtype)
        flat = FEATURE_GRID * FEATURE_GRID * self.fuse_channels + self.extra_features
        self.lstm = [LSTMGates(self.hidden, flat if i == 0 else self.hidden, self.dtype)
                     for i in range(self.lstm_layers)]
        self.actor = nn.Dense(NUM_ACTIONS)
        self.critic_hidden = nn.Dense(64)
        self.critic = nn.Dense(1)

    @property
    def release(self) -> bool:
        """Whether this is the release's form (else the pre-parity one)."""
        return choose({"release": True, "pre_parity": False}, self.form, "trunk form")

    def dropout_channels(self) -> int:
        """Channels of the dropout mask: both sites' (release) or the global map's."""
        return self.glob_channels + (self.fuse_channels if self.release else 0)

    def embed(self, glob, cat_maps, prev_action, drop=None, extra=None):
        """(B, 7, 7, G), (B, C, 49), (B, 6), dropout mask (B, 7, 7, dropout_channels())
        or None, extra (B, extra_features) or None (extra_features 0) -> first-layer LSTM
        input gates (B, 4*hidden)."""
        if (extra is None) != (self.extra_features == 0) or (
                extra is not None and extra.shape[-1] != self.extra_features):
            raise ValueError(f"trunk: extra_features {self.extra_features}, got an extra "
                             f"input of shape {None if extra is None else extra.shape}")
        B = glob.shape[0]
        drop = None if drop is None else cast(drop, self.dtype)
        g = nn.relu(self.global_1x1(glob))
        if drop is not None:
            g = g * drop[..., :self.glob_channels]
        a = self.action_dense(prev_action)
        c = cast(cat_maps, self.dtype)
        if self.release:
            a, c = nn.relu(a), nn.relu(c)
        a = jnp.broadcast_to(a[:, None, None, :], (B, FEATURE_GRID, FEATURE_GRID, a.shape[-1]))
        c = jnp.moveaxis(c, 1, -1).reshape(B, FEATURE_GRID, FEATURE_GRID, -1)
        x = jnp.concatenate([g, c, a], axis=-1)
        x = nn.relu(self.fuse_1x1(x))
        if drop is not None and self.release:
            x = x * drop[..., self.glob_channels:]
        x = x.reshape(B, -1)
        if extra is not None:
            x = jnp.concatenate([x, cast(extra, self.dtype)], axis=-1)
        return self.lstm[0].project(x)

    def recur(self, gates, carry):
        """First-layer input gates (B, 4*hidden), carry -> (logits (B, 6), value (B,),
        new carry, LSTM output (B, hidden))."""
        new_carry, x = self.lstm_step(gates, carry)
        logits, value = self.actor_critic(x)
        return logits, value, new_carry, x

    def lstm_step(self, gates, carry):
        """The recurrence alone: first-layer input gates (B, 4*hidden), carry -> (new
        carry, LSTM output (B, hidden))."""
        new_carry, x = [], None
        for i, layer_carry in enumerate(carry):
            layer_gates = gates if i == 0 else self.lstm[i].project(x)
            layer_carry, x = self.lstm[i].recur(layer_gates, layer_carry)
            new_carry.append(layer_carry)
        return tuple(new_carry), x

    def actor_critic(self, x):
        """LSTM output (..., hidden) -> (logits (..., 6), value (...))."""
        logits = self.actor(x)
        v = self.critic_hidden(x)
        value = self.critic(v if self.release else nn.relu(v))[..., 0]
        return logits, value

    def __call__(self, glob, cat_maps, prev_action, carry):
        """-> (logits (B, 6), value (B,), new carry, LSTM output (B, hidden))."""
        return self.recur(self.embed(glob, cat_maps, prev_action), carry)

    def initial_carry(self, batch: int):
        """Zero LSTM state: a tuple per layer of (c, h), each (batch, hidden)."""
        z = jnp.zeros((batch, self.hidden), jnp.float32)
        return tuple((z, z) for _ in range(self.lstm_layers))


def dropout_mask(key: jax.Array, rate: float, shape) -> jax.Array:
    """Inverted-dropout mask: 0 with probability `rate`, else 1 / (1 - rate) -> float32."""
    keep = jax.random.bernoulli(key, 1.0 - rate, shape)
    return keep.astype(jnp.float32) / (1.0 - rate)


def reset_carry(carry, fresh: jax.Array):
    """Zero the carry of rows where `fresh` (B,) is True (episode starts)."""
    keep = (~fresh)[:, None].astype(jnp.float32)
    return jax.tree_util.tree_map(lambda x: x * keep, carry)
