"""Losses: GAE advantages, the A2C navigation loss, and trial-driven imitation.

All functions take (T, N) arrays (time first) unless stated.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from orgnav_jax.models import model_inputs, reset_carry


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


def il_mask(mode: str, deadlock, last_failed):
    """Steps that get the imitation loss: none | deadlock | all | failed -> (T, N) float."""
    if mode == "none":
        return jnp.zeros_like(deadlock, jnp.float32)
    if mode == "all":
        return jnp.ones_like(deadlock, jnp.float32)
    if mode == "failed":
        return last_failed.astype(jnp.float32)
    return deadlock.astype(jnp.float32)


def imitation_loss(logits, expert_action, mask):
    """Mean over masked steps of CE(log_softmax(logits), expert action); 0 if no step.
    Steps whose expert action is NO_ACTION (< 0) are never counted."""
    mask = mask * (expert_action >= 0)
    logp = jax.nn.log_softmax(logits)
    ce = -jnp.take_along_axis(logp, jnp.maximum(expert_action, 0)[..., None], -1)[..., 0]
    return (ce * mask).sum() / jnp.maximum(mask.sum(), 1.0), mask.sum()


def replay(model, params, scenes, traj, carry0):
    """Re-run the model over a trajectory from the carry at its start -> (logits (T,N,6),
    values (T,N)). The non-recurrent part runs once over all T*N steps (large matmuls);
    only the recurrence is scanned."""
    T, N = traj.fresh.shape
    flat_obs = jax.tree_util.tree_map(lambda x: x.reshape((T * N,) + x.shape[2:]), traj.obs)
    gates = model.apply(params, model_inputs(scenes, flat_obs), method=model.embed)

    def body(carry, x):
        g, fresh = x
        logits, value, carry, _ = model.apply(params, g, reset_carry(carry, fresh),
                                              method=model.recur)
        return carry, (logits, value)

    _, (logits, values) = jax.lax.scan(body, carry0, (gates.reshape(T, N, -1), traj.fresh))
    return logits, values


def a2c_loss(params, model, scenes, traj, carry0, advantages, returns, cfg):
    """Navigation loss (policy gradient + value + entropy) + il_weight * IL -> (loss, aux)."""
    logits, values = replay(model, params, scenes, traj, carry0)
    logp_all = jax.nn.log_softmax(logits)
    logp = jnp.take_along_axis(logp_all, traj.action[..., None], -1)[..., 0]
    policy_loss = -(jax.lax.stop_gradient(advantages) * logp).mean()
    value_loss = 0.5 * ((returns - values) ** 2).mean()
    entropy = -(jnp.exp(logp_all) * logp_all).sum(-1).mean()
    mask = il_mask(cfg.il, traj.obs.deadlock, traj.last_failed)
    il, il_steps = imitation_loss(logits, traj.expert_action, mask)
    loss = (policy_loss + cfg.value_coef * value_loss - cfg.entropy_coef * entropy
            + cfg.il_weight * il)
    aux = {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy,
           "il_loss": il, "il_steps": il_steps}
    return loss, aux
