"""Expert tables: shortest paths to a state where each category is visible (JAX).

Bellman-Ford relaxation on the unit-cost action graph, batched over rooms and
categories under one jit: dist[s, c] = 0 where c is visible, otherwise
1 + min over the 5 moving actions of dist[next_state[s, a], c]. Iterates until nothing
changes (at most S times).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from orgnav_jax.constants import DONE
from orgnav_jax.scenes.sceneset.fields import NO_ACTION, UNREACHABLE


def _room_tables(next_state: jax.Array, visible: jax.Array, valid: jax.Array):
    """One room: next_state (S, A), visible (S, C), valid (S,) -> dist, action (S, C)."""
    moves = next_state[:, :DONE]                                    # (S, 5)
    start = jnp.where(visible & valid[:, None], 0, UNREACHABLE).astype(jnp.int32)

    def relax(dist):
        best = jnp.min(dist[moves], axis=1)                         # (S, C)
        return jnp.minimum(dist, jnp.minimum(best + 1, UNREACHABLE))

    def cond(carry):
        dist, changed, it = carry
        return changed & (it < next_state.shape[0])

    def body(carry):
        dist, _, it = carry
        new = relax(dist)
        return new, jnp.any(new != dist), it + 1

    dist, _, _ = jax.lax.while_loop(cond, body, (start, jnp.array(True), jnp.array(0)))
    succ = dist[moves]                                              # (S, 5, C)
    on_path = succ == (dist - 1)[:, None, :]
    first = jnp.argmax(on_path, axis=1).astype(jnp.int32)           # lowest action index
    action = jnp.where(dist == 0, DONE, first)
    action = jnp.where(dist >= UNREACHABLE, NO_ACTION, action)
    return dist, action


@jax.jit
def expert_tables(next_state: jax.Array, visible: jax.Array, state_valid: jax.Array):
    """Batched over rooms: (N, S, A), (N, S, C), (N, S) -> dist (N, S, C) int32 (UNREACHABLE
    where no visible state can be reached) and expert_action (N, S, C) int32 (DONE at
    distance 0, NO_ACTION where unreachable)."""
    return jax.vmap(_room_tables)(next_state, visible, state_valid)
