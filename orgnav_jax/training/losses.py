"""Losses: GAE advantages, the A2C navigation loss, and trial-driven imitation.

All functions take (T, N) arrays (time first) unless stated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from orgnav_jax.errors import choose
from orgnav_jax.models import dropout_mask, model_inputs, reset_carry


def gae(reward, value, done, last_value, gamma: float, lam: float):
    """Generalized advantage estimates -> (advantages (T, N), returns (T, N)).
    `done[t]` ends the episode after step t (no bootstrap across it)."""
    def body(next_adv_value, x):
        next_adv, next_value = next_adv_value
        r, v, d = x
        nonterminal = 1.0 - d.astype(jnp.float32)
        delta = r + gamma * next_value * nonterminal - v
        adv = delta + gamma * lam * nonterminal * next_adv
        return (adv, v), adv

    _, adv = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value),
                          (reward, value, done), reverse=True)
    return adv, adv + value


def il_mask(mode: str, step: str, traj):
    """Steps of a Trajectory that get the imitation loss -> (T, N) float32.

    mode: none | deadlock | all | failed. step, for deadlock and failed: "state" is the
    step taken at a deadlock state (the state was visited before, or the previous action
    failed); "cause" is the step whose action failed, led into a visited state or was
    Done (the release's choice). Either way the label is the expert's action at the
    state where the supervised action was chosen."""
    shape = traj.action.shape
    by_step = {"deadlock": {"state": lambda: traj.obs.deadlock, "cause": lambda: traj.caused},
               "failed": {"state": lambda: traj.last_failed, "cause": lambda: traj.failed}}
    flags = choose({"none": lambda: jnp.zeros(shape, bool),
                    "all": lambda: jnp.ones(shape, bool),
                    **{m: choose(s, step, "IL step") for m, s in by_step.items()}},
                   mode, "IL mode")()
    return flags.astype(jnp.float32)


def imitation_loss(logits, expert_action, mask, norm: str = "masked_mean"):
    """CE(log_softmax(logits), expert action) over masked steps -> (loss, IL steps).
    norm "masked_mean": mean over the masked steps (0 if none); "per_step": their sum
    divided by all steps (mask.size), so that one IL step weighs as much as one step of
    a per-step mean such as the policy-gradient term (the release sums both over steps).
    Steps whose expert action is NO_ACTION (< 0) are never counted."""
    mask = mask * (expert_action >= 0)
    logp = jax.nn.log_softmax(logits)
    ce = -jnp.take_along_axis(logp, jnp.maximum(expert_action, 0)[..., None], -1)[..., 0]
    denom = choose({"masked_mean": lambda: jnp.maximum(mask.sum(), 1.0),
                    "per_step": lambda: mask.size}, norm, "IL normalization")()
    return (ce * mask).sum() / denom, mask.sum()


def replay(model, params, scenes, traj, carry0, dropout: float = 0.0,
           batch_major: bool = False):
    """Re-run the model over a trajectory from the carry at its start -> (logits (T,N,6),
    values (T,N)). The non-recurrent part runs once over all T*N steps (large matmuls);
    only the recurrence is scanned. With dropout, each step's masks are rebuilt from the
    key the rollout kept (traj.drop_key), so the replay sees exactly the rollout's masks.
    batch_major flattens the steps env-major (N*T) rather than time-major (T*N): with the
    env axis sharded over devices (training/scale.py) the flat axis then stays sharded,
    where a time-major flattening makes XLA gather every step onto every device."""
    T, N = traj.fresh.shape
    if batch_major:
        flat = lambda x: jnp.swapaxes(x, 0, 1).reshape((N * T,) + x.shape[2:])
        unflat = lambda x: jnp.swapaxes(x.reshape((N, T) + x.shape[1:]), 0, 1)
    else:
        flat = lambda x: x.reshape((T * N,) + x.shape[2:])
        unflat = lambda x: x.reshape((T, N) + x.shape[1:])
    inputs = model_inputs(scenes, jax.tree_util.tree_map(flat, traj.obs))
    if dropout:
        masks = jax.vmap(lambda k: dropout_mask(k, dropout, model.dropout_shape(N)))(
            traj.drop_key)
        inputs = inputs._replace(drop=flat(masks))
    gates = model.apply(params, inputs, method=model.embed)

    def body(carry, x):
        g, fresh = x
        logits, value, carry, _ = model.apply(params, g, reset_carry(carry, fresh),
                                              method=model.recur)
        return carry, (logits, value)

    _, (logits, values) = jax.lax.scan(body, carry0, (unflat(gates), traj.fresh))
    return logits, values


def a2c_loss(params, model, scenes, traj, carry0, advantages, returns, cfg,
             batch_major: bool = False):
    """Navigation loss (policy gradient + value + entropy) + il_weight * IL -> (loss, aux).
    batch_major: see replay."""
    logits, values = replay(model, params, scenes, traj, carry0, cfg.dropout, batch_major)
    logp_all = jax.nn.log_softmax(logits)
    logp = jnp.take_along_axis(logp_all, traj.action[..., None], -1)[..., 0]
    policy_loss = -(jax.lax.stop_gradient(advantages) * logp).mean()
    value_loss = 0.5 * ((returns - values) ** 2).mean()
    entropy = -(jnp.exp(logp_all) * logp_all).sum(-1).mean()
    il, il_steps = imitation_loss(logits, traj.expert_action,
                                  il_mask(cfg.il, cfg.il_step, traj), cfg.il_norm)
    loss = (policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
            + cfg.il_weight * il)
    if cfg.optim == "release":     # the release sums its losses over the steps of an
        loss = loss * traj.fresh.shape[0]   # episode: sum over time, mean over envs
    aux = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
           "il_loss": il, "il_steps": il_steps}
    return loss, aux
