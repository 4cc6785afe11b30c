"""The runner state and the vectorized rollout (a lax.scan over T env steps).

RunnerState holds everything a run needs to continue bit-for-bit: network parameters,
optimizer state, env states, LSTM carries, per-env episode returns, the PRNG key and
the update count. A Trajectory holds what the loss needs to replay the rollout.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from orgnav_jax import env
from orgnav_jax.constants import DONE
from orgnav_jax.models import dropout_mask, model_inputs, previous_action, reset_carry


@struct.dataclass
class RunnerState:
    params: Any
    opt_state: Any
    env_state: env.EnvState   # (N,) batched
    carry: Any                # LSTM carry, leading axis N
    fresh: jax.Array          # (N,) bool: the env's episode starts at this step
    ep_return: jax.Array      # (N,) float32 return so far in the running episode
    key: jax.Array
    update: jax.Array         # () int32 updates done


@struct.dataclass
class Trajectory:
    """(T, N) per-step arrays (obs is a batched Observation with leading (T, N))."""
    obs: env.Observation      # prev_action: the model's previous-action input at the step
    fresh: jax.Array
    action: jax.Array
    reward: jax.Array
    done: jax.Array
    value: jax.Array
    expert_action: jax.Array  # (T, N) int32 expert's action at the step's state
    last_failed: jax.Array    # (T, N) bool: the previous action failed (part of deadlock)
    failed: jax.Array         # (T, N) bool: this step's action failed
    caused: jax.Array         # (T, N) bool: this step's action failed, led to a state
                              #   visited before in the episode, or was Done (il_step cause)
    drop_key: jax.Array | None  # (T, key) the key of each step's dropout masks, or None


@struct.dataclass
class EpisodeStats:
    """Sums over episodes that finished during a chunk (fixed shapes, inside jit)."""
    count: jax.Array
    success: jax.Array
    spl: jax.Array
    ret: jax.Array
    length: jax.Array

    @classmethod
    def zeros(cls) -> "EpisodeStats":
        z = jnp.float32(0)
        return cls(z, z, z, z, z)


def caused_deadlock(action, info):
    """(N,) bool: the action failed, led into a state visited before in the episode, or
    was Done (the release's trial-driven IL supervises these steps)."""
    return info["failed"] | info["revisited"] | (action == DONE)


def train_inputs(model, scenes, obs, key, dropout: float):
    """model_inputs with this step's dropout mask drawn from `key` (none if dropout 0)."""
    inputs = model_inputs(scenes, obs)
    if dropout == 0.0:
        return inputs
    return inputs._replace(drop=dropout_mask(key, dropout,
                                             model.dropout_shape(obs.state.shape[0])))


def rollout(model, runner: RunnerState, scenes, env_params: env.EnvParams, length: int,
            dropout: float = 0.0):
    """Act for `length` steps in every env -> (runner, trajectory, last value (N,), stats).
    With dropout > 0 each step draws its masks from a key kept in the trajectory."""
    num_envs = runner.fresh.shape[0]
    v_step = jax.vmap(env.step, in_axes=(0, 0, 0, None, None))
    v_observe = jax.vmap(env.observe, in_axes=(0, None))

    def body(carry, _):
        runner, stats = carry
        key, k_act, k_env, k_drop = jax.random.split(runner.key, 4)
        lstm = reset_carry(runner.carry, runner.fresh)
        obs = v_observe(runner.env_state, scenes)
        obs = obs.replace(prev_action=previous_action(model, obs.prev_action, lstm))
        logits, value, lstm, _ = model.apply(
            runner.params, train_inputs(model, scenes, obs, k_drop, dropout), lstm)
        action = jax.random.categorical(k_act, logits).astype(jnp.int32)
        st = runner.env_state
        expert = scenes.expert_action[st.state, st.target].astype(jnp.int32)
        _, env_state, reward, done, info = v_step(jax.random.split(k_env, num_envs), st,
                                                   action, scenes, env_params)
        ep_return = runner.ep_return + reward
        spl = info["success"] * info["optimal_len"] / jnp.maximum(
            jnp.maximum(info["path_len"], info["optimal_len"]), 1)
        d = done.astype(jnp.float32)
        stats = EpisodeStats(stats.count + d.sum(), stats.success + (d * info["success"]).sum(),
                             stats.spl + (d * spl).sum(), stats.ret + (d * ep_return).sum(),
                             stats.length + (d * info["steps"]).sum())
        traj = Trajectory(obs, runner.fresh, action, reward, done, value, expert,
                          st.last_failed, info["failed"], caused_deadlock(action, info),
                          k_drop if dropout else None)
        runner = runner.replace(env_state=env_state, carry=lstm, fresh=done,
                                ep_return=jnp.where(done, 0.0, ep_return), key=key)
        return (runner, stats), traj

    (runner, stats), traj = jax.lax.scan(body, (runner, EpisodeStats.zeros()), None,
                                         length=length)
    obs = v_observe(runner.env_state, scenes)
    # the bootstrap value, in train mode too (a key of its own, not used by any step)
    k_last = jax.random.fold_in(runner.key, 1)
    _, last_value, _, _ = model.apply(runner.params,
                                      train_inputs(model, scenes, obs, k_last, dropout),
                                      reset_carry(runner.carry, runner.fresh))
    return runner, traj, last_value, stats
