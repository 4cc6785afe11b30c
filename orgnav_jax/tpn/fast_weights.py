"""Per-episode fast weights for TPN's test-time update.

A scope of the navigation model's variables (the actor head, the trunk above the
encoder, or all) is split off and copied once per environment; those copies are the only
parameters a test-time update changes, so an update in one episode never reaches another
episode or environment. Everything here works on one environment; callers vmap.

    scoped, rest = split_scope(variables, "actor")        # flat dicts {path tuple: array}
    logits, carry, h = forward(model, scoped, rest, inputs, carry)      # one env, no batch
    scoped = sgd_step(model, scoped, rest, inputs, carry, target, lr)   # CE(policy, target)
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import traverse_util

SCOPE_PATHS = {"actor": ("params", "trunk", "actor"),     # the policy head
               "trunk": ("params", "trunk"),              # everything above the encoder
               "all": ("params",)}


def split_scope(variables, scope: str):
    """Model variables -> (scoped, rest): flat dicts {path: array}; `scoped` holds the
    leaves under SCOPE_PATHS[scope]."""
    if scope not in SCOPE_PATHS:
        raise ValueError(f"unknown test-time update scope {scope!r}: expected one of "
                         f"{sorted(SCOPE_PATHS)}")
    prefix = SCOPE_PATHS[scope]
    flat = traverse_util.flatten_dict(variables)
    scoped = {k: v for k, v in flat.items() if k[:len(prefix)] == prefix}
    if not scoped:
        raise ValueError(f"scope {scope!r}: the model has no parameters under {prefix}")
    return scoped, {k: v for k, v in flat.items() if k not in scoped}


def merge_scope(scoped, rest):
    """Inverse of split_scope -> model variables."""
    return traverse_util.unflatten_dict({**rest, **scoped})


def forward(model, scoped, rest, inputs, carry):
    """One environment's step with its own fast weights: inputs and carry without a batch
    axis -> (logits (6,), new carry, LSTM output (hidden,))."""
    add = lambda t: jax.tree_util.tree_map(lambda x: x[None], t)
    logits, _, carry, h = model.apply(merge_scope(scoped, rest), add(inputs), add(carry))
    return logits[0], jax.tree_util.tree_map(lambda x: x[0], carry), h[0]


def policy_ce(logits, target):
    """Cross-entropy of a target action under log_softmax(logits) (not of probabilities:
    the release's double softmax is a known defect)."""
    return -jax.nn.log_softmax(logits)[target]


def sgd_step(model, scoped, rest, inputs, carry, target, lr):
    """One SGD step of CE(policy logits, target) on the fast weights (one environment)."""
    grads = jax.grad(lambda s: policy_ce(forward(model, s, rest, inputs, carry)[0],
                                         target))(scoped)
    return jax.tree_util.tree_map(lambda p, g: p - lr * g, scoped, grads)


def scope_size(variables, scope: str) -> int:
    """Number of parameters one environment's fast weights hold."""
    return sum(int(v.size) for v in split_scope(variables, scope)[0].values())
