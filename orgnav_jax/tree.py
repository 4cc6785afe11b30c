"""Pytree helpers shared by the evaluation scan and the TPN's fast weights.

    where_rows(mask (B,), new, old) -> new where mask, else old (row by row)
    tile(tree, B)                   -> every leaf repeated along a new leading axis B
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def where_rows(mask, new, old):
    """Per-row select between two pytrees with leading axis B: new where mask (B,)."""
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b), new, old)


def tile(tree, batch: int):
    """Every leaf (...) -> (batch, ...), broadcast (no copy until written)."""
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), tree)
