"""The external memory: which steps are deadlocks (shared by stage 2 and test time).

    vision = detector_init(memory, batch, episode_cap)
    is_deadlock, vision = detect(memory, vision, obs.deadlock, inputs.glob, fresh)

`memory` is a tpn.config.DeadlockMemory (or anything with its fields: deadlock,
cosine_threshold, signature_dim, such as the test-time config).

"visited" is the release's detector: the env's flag (state visited before in the episode,
or the last move failed). "cosine" is the paper's (Sec. 3.4, "External Memory"): the
global feature map is near-identical (cosine >= threshold) to one recorded earlier in the
same episode:

    glob (B, 7, 7, G) -> flatten (B, 49 G) @ P (49 G, dim) -> sig (B, dim)
    VisionMemory: unit sigs (B, M, dim), count (B,)

P is a fixed, parameter-free Gaussian matrix (seeded), so memory costs dim floats per step
instead of 49 G. By Johnson-Lindenstrauss, random projections approximately preserve inner
products and norms, hence cosine similarity: near-identical features stay near-identical.
(With dim = 64, the projected cosine scatters by about (1 - c^2) / 8 around the true c.)
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from orgnav_jax.errors import choose


@functools.lru_cache(maxsize=8)
def signature_projection(in_dim: int, dim: int = 64, seed: int = 0) -> np.ndarray:
    """Fixed Gaussian projection (in_dim, dim), entries N(0, 1/dim); a numpy constant,
    made once per shape (inside jit it is a compile-time constant)."""
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((in_dim, dim)) / np.sqrt(dim)).astype(np.float32)


def global_signature(glob: jax.Array, projection: jax.Array) -> jax.Array:
    """glob (B, 7, 7, G) global feature map, projection (49 G, dim) -> sig (B, dim)."""
    return glob.reshape(glob.shape[0], -1) @ projection


def unit(x: jax.Array, eps: float = 1e-12) -> jax.Array:
    """(..., d) -> (..., d) divided by its norm; zero vectors stay zero (no NaN)."""
    return x * jax.lax.rsqrt(jnp.maximum(jnp.sum(x * x, -1, keepdims=True), eps))


@struct.dataclass
class VisionMemory:
    """sigs (B, M, dim): unit-norm signatures of this episode's states, slots 0..count-1
    valid; count (B,) int32."""
    sigs: jax.Array
    count: jax.Array


def vision_memory_init(batch: int, size: int, dim: int = 64) -> VisionMemory:
    """Empty memory of `size` signatures per env."""
    return VisionMemory(jnp.zeros((batch, size, dim)), jnp.zeros((batch,), jnp.int32))


def vision_memory_reset(mem: VisionMemory, fresh: jax.Array) -> VisionMemory:
    """fresh (B,) bool: those rows forget their episode (count 0; stale sigs are masked)."""
    return mem.replace(count=jnp.where(fresh, 0, mem.count))


def vision_deadlock(mem: VisionMemory, sig: jax.Array, threshold: float = 0.99):
    """sig (B, dim) -> (is_deadlock (B,) bool, mem). Deadlock where the max cosine between
    sig and the first `count` stored sigs is >= threshold (never on an empty memory; a
    zero sig has cosine 0 with everything). Then sig is appended; dropped when full (the
    memory keeps the episode's first M states)."""
    B, M = mem.sigs.shape[:2]
    u = unit(sig)
    cos = jnp.einsum("bmd,bd->bm", mem.sigs, u)
    valid = jnp.arange(M)[None, :] < mem.count[:, None]
    hit = jnp.any(valid & (cos >= threshold), axis=-1)
    slot = jnp.where(mem.count < M, mem.count, M)                         # M: dropped
    sigs = mem.sigs.at[jnp.arange(B), slot].set(u, mode="drop")
    return hit, mem.replace(sigs=sigs, count=jnp.minimum(mem.count + 1, M))


def detector_init(cfg, batch: int, episode_cap: int):
    """-> the detector's per-episode state (None for "visited")."""
    return choose({"visited": lambda: None,
                   "cosine": lambda: vision_memory_init(batch, episode_cap + 1,
                                                        cfg.signature_dim)},
                  cfg.deadlock, "deadlock detector")()


def detect(cfg, vision, env_deadlock, glob, fresh):
    """env_deadlock (B,) bool, glob (B, 7, 7, G), fresh (B,) -> (deadlock (B,), vision)."""
    def cosine():
        projection = signature_projection(glob[0].size, cfg.signature_dim)
        memory = vision_memory_reset(vision, fresh)
        return vision_deadlock(memory, global_signature(glob, projection),
                               cfg.cosine_threshold)
    return choose({"visited": lambda: (env_deadlock, vision), "cosine": cosine},
                  cfg.deadlock, "deadlock detector")()
