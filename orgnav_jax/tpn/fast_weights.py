"""Per-episode fast weights for TPN's test-time update.

A scope of the navigation model's variables (the actor head, the trunk above the
encoder, or all) is split off and copied once per environment; those copies are the only
parameters a test-time update changes, so an update in one episode never reaches another
episode or environment.

A step is split in two: `shared` runs, batched, everything the fast weights do not
touch (for the actor scope: the whole model up to the LSTM output; otherwise nothing),
and `per_env` runs the rest for one environment with its own fast weights (callers vmap
it). Only `per_env` is differentiated and re-run after an update.

    scoped, rest = split_scope(variables, "actor")        # flat dicts {path tuple: array}
    shared, per_env = split_step(model, "actor")
    features = shared(variables, inputs, carry)                        # batched
    logits, carry, h = per_env(scoped, rest, features_b)               # one env
    scoped = sgd_step(per_env, scoped, rest, features_b, target, lr)   # CE(policy, target)
"""

from __future__ import annotations

import functools

import jax
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


def _one(tree):
    return jax.tree_util.tree_map(lambda x: x[None], tree)


def _unbatch(tree):
    return jax.tree_util.tree_map(lambda x: x[0], tree)


@functools.cache
def split_step(model, scope: str):
    """-> (shared, per_env) for a NavModel and a scope (see module docstring).

    shared(variables, inputs (B, ...), carry (B, ...)) -> features (B, ...)
    per_env(scoped, rest, features without the batch axis) -> (logits (6,), carry, h)
    """
    if scope == "actor":
        def shared(variables, inputs, carry):
            _, _, carry, h = model.apply(variables, inputs, carry)
            return h, carry

        def per_env(scoped, rest, features):
            h, carry = features
            logits = model.apply(merge_scope(scoped, rest), h[None],
                                 method=lambda m, x: m.trunk.actor(x))
            return logits[0], carry, h
    else:
        def shared(variables, inputs, carry):
            return inputs, carry

        def per_env(scoped, rest, features):
            inputs, carry = features
            logits, _, carry, h = model.apply(merge_scope(scoped, rest), _one(inputs),
                                              _one(carry))
            return logits[0], _unbatch(carry), h[0]
    return shared, per_env


def policy_ce(logits, target):
    """Cross-entropy of a target action under log_softmax(logits) (not of probabilities:
    the release's double softmax is a known defect)."""
    return -jax.nn.log_softmax(logits)[target]


def sgd_step(per_env, scoped, rest, features, target, lr):
    """One SGD step of CE(policy logits, target) on one environment's fast weights."""
    grads = jax.grad(lambda s: policy_ce(per_env(s, rest, features)[0], target))(scoped)
    return jax.tree_util.tree_map(lambda p, g: p - lr * g, scoped, grads)


def scope_size(variables, scope: str) -> int:
    """Number of parameters one environment's fast weights hold."""
    return sum(int(v.size) for v in split_scope(variables, scope)[0].values())
