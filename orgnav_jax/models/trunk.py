"""The navigation trunk shared by every model (paper / authors' release).

global map (B, 7, 7, G) -> Dense(glob_channels) ReLU
previous action (B, 6)  -> Dense(action_embed), tiled to 7x7
category maps (B, C, 49) -> 7x7xC
concat -> Dense(fuse_channels) ReLU -> flatten (B, 49*fuse) -> LSTM x layers (hidden)
-> actor Dense(6) logits; critic Dense(64) ReLU Dense(1).
1x1 convolutions are written as Dense over channels (much faster on CPU under scan).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS


class Trunk(nn.Module):
    glob_channels: int = 64
    action_embed: int = 10
    fuse_channels: int = 64
    hidden: int = 512
    lstm_layers: int = 1

    @nn.compact
    def __call__(self, glob, cat_maps, prev_action, carry, train: bool = False):
        """-> (logits (B, 6), value (B,), new carry, lstm output (B, hidden))."""
        B = glob.shape[0]
        g = nn.relu(nn.Dense(self.glob_channels, name="global_1x1")(glob))
        a = nn.Dense(self.action_embed, name="action_embed")(prev_action)
        a = jnp.broadcast_to(a[:, None, None, :], (B, FEATURE_GRID, FEATURE_GRID, a.shape[-1]))
        c = jnp.moveaxis(cat_maps, 1, -1).reshape(B, FEATURE_GRID, FEATURE_GRID, -1)
        x = jnp.concatenate([g, c, a], axis=-1)
        x = nn.relu(nn.Dense(self.fuse_channels, name="fuse_1x1")(x)).reshape(B, -1)
        new_carry = []
        for i, layer_carry in enumerate(carry):
            layer_carry, x = nn.OptimizedLSTMCell(self.hidden, name=f"lstm_{i}")(layer_carry, x)
            new_carry.append(layer_carry)
        logits = nn.Dense(NUM_ACTIONS, name="actor")(x)
        v = nn.relu(nn.Dense(64, name="critic_hidden")(x))
        value = nn.Dense(1, name="critic")(v)[:, 0]
        return logits, value, tuple(new_carry), x

    def initial_carry(self, batch: int):
        """Zero LSTM state: a tuple per layer of (c, h), each (batch, hidden)."""
        z = jnp.zeros((batch, self.hidden), jnp.float32)
        return tuple((z, z) for _ in range(self.lstm_layers))


def reset_carry(carry, fresh: jax.Array):
    """Zero the carry of rows where `fresh` (B,) is True (episode starts)."""
    keep = (~fresh)[:, None].astype(jnp.float32)
    return jax.tree_util.tree_map(lambda x: x * keep, carry)
