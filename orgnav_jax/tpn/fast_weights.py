"""Per-episode fast weights for TPN's test-time update: dense copies.

A scope of the navigation model's variables (the actor head, the trunk above the
encoder, or all) is split off and copied once per environment; those copies are the only
parameters a test-time update changes, so an update in one episode never reaches another
episode or environment. This is the test-time path of the actor scope (6 x H weights per
episode, and the model up to the LSTM runs once, shared); for the trunk or all parameters
a full copy per episode is memory-bound (50x slower than plain evaluation), and
tpn/lowrank.py keeps them as low-rank deltas instead. `DenseFastWeights` stays the
reference those are tested against. The gradient is truncated to the current step (the
LSTM carry from the previous step is an input, a constant).

A step is split in two: `shared` runs, batched, everything the fast weights do not
touch (for the actor scope: the whole model up to the LSTM output; otherwise nothing),
and `per_env` runs the rest for one environment with its own fast weights (callers vmap
it). Only `per_env` is differentiated and re-run after an update.

    scoped, rest = split_scope(variables, "actor")        # flat dicts {path tuple: array}
    shared, per_env = split_step(model, "actor")
    features = shared(variables, inputs, carry)                        # batched
    logits, carry, h = per_env(scoped, rest, features_b)               # one env
    scoped = sgd_step(per_env, scoped, rest, features_b, target, lr)   # CE(policy, target)

    fw = DenseFastWeights(model, "all")        # the step interface tpn/test_time.py drives
    fast = fw.init(B, variables)
    logits, lstm, fast, aux = fw.step(variables, fast, inputs, carry, decide, lr)
"""

from __future__ import annotations


import jax
from flax import traverse_util

from orgnav_jax.compile_cache import compiled_once
from orgnav_jax.tree import tile, where_rows

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


@compiled_once
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


def policy_ce_grad(logits, target):
    """Gradient of policy_ce with respect to the logits, batched: (B, 6), (B,) -> (B, 6)."""
    return jax.nn.softmax(logits) - jax.nn.one_hot(target, logits.shape[-1])


def sgd_step(per_env, scoped, rest, features, target, lr):
    """One SGD step of CE(policy logits, target) on one environment's fast weights."""
    grads = jax.grad(lambda s: policy_ce(per_env(s, rest, features)[0], target))(scoped)
    return jax.tree_util.tree_map(lambda p, g: p - lr * g, scoped, grads)


def scope_size(variables, scope: str) -> int:
    """Number of parameters one environment's fast weights hold."""
    return sum(int(v.size) for v in split_scope(variables, scope)[0].values())


PLACEMENTS = ("state", "release")


class DenseFastWeights:
    """Full per-episode copies of a scope's parameters (see module docstring), with the
    step interface of lowrank.LowRankFastWeights.

    placement "state" (ours): a step's update is taken on that step's logits, which are
    re-run with the new weights. "release" (the ECCV release's): a step's update is
    computed on its logits but kept pending, and the next step applies it first when its
    `commit` says so (s_{t+1} is a deadlock); the step is not re-run. The fast weights
    are then (weights, weights after the pending update, pending (B,) bool)."""

    def __init__(self, model, scope: str, placement: str = "state"):
        if placement not in PLACEMENTS:
            raise ValueError(f"TPN placement {placement!r}: expected one of {PLACEMENTS}")
        self.model, self.scope, self.placement = model, scope, placement
        self.shared, per_env = split_step(model, scope)
        self.per_env = per_env
        self.v_per_env = jax.vmap(per_env, in_axes=(0, None, 0))
        self.v_sgd = jax.vmap(sgd_step, in_axes=(None, 0, None, 0, 0, None))

    def __hash__(self):
        return hash((self.model, self.scope, self.placement))

    def __eq__(self, other):
        return isinstance(other, DenseFastWeights) and (
            self.model, self.scope, self.placement) == (other.model, other.scope,
                                                        other.placement)

    def init(self, batch: int, base):
        w = tile(split_scope(base, self.scope)[0], batch)
        if self.placement == "release":
            return w, w, jax.numpy.zeros(batch, bool)
        return w

    def reset(self, base, fast, mask):
        """mask (B,) bool: those rows go back to the trained weights."""
        return where_rows(mask, self.init(mask.shape[0], base), fast)

    def step(self, base, fast, inputs, carry, decide, lr, commit=None):
        """As LowRankFastWeights.step: -> (logits (B, 6), carry, fast, aux)."""
        _, rest = split_scope(base, self.scope)
        features = self.shared(base, inputs, carry)
        if self.placement == "release":
            w, after, pending = fast
            w = where_rows(pending & commit, after, w)       # the previous step's update
            logits, lstm, h = self.v_per_env(w, rest, features)
            target, update, aux = decide(logits, h)
            after = self.v_sgd(self.per_env, w, rest, features, target, lr)
            return logits, lstm, (w, after, update), aux
        logits, lstm, h = self.v_per_env(fast, rest, features)
        target, update, aux = decide(logits, h)
        fast = where_rows(update, self.v_sgd(self.per_env, fast, rest, features, target, lr),
                          fast)
        logits2, lstm2, _ = self.v_per_env(fast, rest, features)   # act with the new weights
        logits, lstm = where_rows(update, (logits2, lstm2), (logits, lstm))
        return logits, lstm, fast, aux

    def materialize(self, base, fast):
        """-> {path: (B, ...)} the scope's weights each episode acts with (placement
        "release": before its pending update)."""
        return fast[0] if self.placement == "release" else fast
