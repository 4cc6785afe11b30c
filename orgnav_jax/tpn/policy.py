"""The navigation policy with TPN's test-time update, as an evaluation Policy.

At every step of every episode (vmapped over environments, inside the jitted evaluation
scan): the base model runs with the episode's own fast weights; the TPN reads its
internal memory; on a deadlock step (or every step, when="all") the target is the TPN's
argmax (or a random action, target="random"), the fast weights take one SGD step of
CE(policy logits, target), and the agent acts greedily with the updated weights. Fast
weights are reset to the trained parameters at each episode start.

    policy, params, nav_cfg, tpn_cfg = load_tpn_policy("runs/baseline-small/tpn")
    evaluation.evaluate(policy, params, scenes, episodes)
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from orgnav_jax.constants import NUM_ACTIONS
from orgnav_jax.env import EnvParams
from orgnav_jax.evaluation import Policy, where_rows
from orgnav_jax.models import model_inputs, reset_carry
from orgnav_jax.models.tpn import TPN, memory_init, memory_record, memory_reset
from orgnav_jax.tpn.config import TPNConfig, get_tpn_config, load_tpn_config
from orgnav_jax.tpn.deadlock import detect, detector_init
from orgnav_jax.tpn.fast_weights import scope_size, sgd_step, split_scope, split_step


@struct.dataclass
class TPNCarry:
    """Per-environment state of the policy (leading axis B everywhere)."""
    lstm: Any           # the base model's LSTM carry
    fast: Any           # the episode's fast weights (the scope's parameters)
    memory: Any         # models.tpn.TPNMemory (internal memory)
    vision: Any         # the deadlock detector's memory (None for "visited")
    updates: jax.Array  # (B,) int32 test-time updates in the running episode


def build_tpn(nav_cfg, cfg: TPNConfig) -> TPN:
    return TPN(hidden=nav_cfg.hidden, action_embed=cfg.action_embed, mlp=cfg.mlp,
               top_k=cfg.top_k)


def tile(tree, batch: int):
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), tree)


@functools.cache
def tpn_policy(model, tpn: TPN, cfg: TPNConfig, name: str = "TPN") -> Policy:
    """policy_params = {"base": navigation variables, "tpn": TPN variables}."""
    shared, per_env = split_step(model, cfg.scope)
    v_per_env = jax.vmap(per_env, in_axes=(0, None, 0))
    v_sgd = jax.vmap(sgd_step, in_axes=(None, 0, None, 0, 0, None))

    def init(batch, params):
        scoped, _ = split_scope(params["base"], cfg.scope)
        size = max(EnvParams.evaluation().max_steps)       # the longest test episode
        return TPNCarry(model.initial_carry(batch), tile(scoped, batch),
                        memory_init(batch, size, tpn.hidden), detector_init(cfg, batch, size),
                        jnp.zeros(batch, jnp.int32))

    def act(params, carry: TPNCarry, obs, key, scenes, fresh):
        base_scoped, rest = split_scope(params["base"], cfg.scope)
        fast = where_rows(fresh, tile(base_scoped, fresh.shape[0]), carry.fast)
        inputs = model_inputs(scenes, obs)
        features = shared(params["base"], inputs, reset_carry(carry.lstm, fresh))
        logits, lstm, h = v_per_env(fast, rest, features)
        tpn_logits, r, memory = tpn.apply(params["tpn"], h, memory_reset(carry.memory, fresh),
                                          method=tpn.step_logits)
        deadlock, vision = detect(cfg, carry.vision, obs.deadlock, inputs.glob, fresh)
        update = deadlock if cfg.when == "deadlock" else jnp.ones_like(deadlock)
        if cfg.target == "tpn":
            target = jnp.argmax(tpn_logits, -1)
        else:
            target = jax.random.randint(key, fresh.shape, 0, NUM_ACTIONS)
        fast = where_rows(update, v_sgd(per_env, fast, rest, features, target, cfg.tpn_lr),
                           fast)
        # act with the updated weights (only rows that updated change)
        logits2, lstm2, _ = v_per_env(fast, rest, features)
        logits, lstm = where_rows(update, (logits2, lstm2), (logits, lstm))
        memory = memory_record(memory, r, jax.nn.softmax(logits))
        updates = jnp.where(fresh, 0, carry.updates) + update.astype(jnp.int32)
        return jnp.argmax(logits, -1).astype(jnp.int32), TPNCarry(lstm, fast, memory, vision,
                                                                   updates)

    return Policy(name, init, act)


def load_tpn_policy(run_dir: str | Path, **test_time):
    """-> (Policy, {"base", "tpn"} params, navigation config, TPN config) of a stage-2
    run (its best-on-val TPN and its base's best-on-val model); `test_time` overrides
    test-time fields (tpn_lr, scope, when, target, deadlock, cosine_threshold)."""
    from orgnav_jax.training.checkpoints import RunCheckpoints
    from orgnav_jax.training.policy import load_run_model
    cfg = load_tpn_config(run_dir)
    cfg = get_tpn_config(**{**dataclasses.asdict(cfg), **test_time})
    model, base_params, nav_cfg = load_run_model(cfg.base_dir)
    tpn = build_tpn(nav_cfg, cfg)
    like = init_tpn_params(tpn, nav_cfg, jax.random.PRNGKey(0))
    ckpt = RunCheckpoints(run_dir)
    if ckpt.best.latest_step() is None:
        raise FileNotFoundError(f"{run_dir}: no best-on-val TPN checkpoint yet")
    tpn_params, _ = ckpt.restore(like, best=True)
    name = f"{nav_cfg.model}+TPN" + ("" if cfg.when == "deadlock" else f"-{cfg.when}") + \
        ("" if cfg.target == "tpn" else f"-{cfg.target}")
    return tpn_policy(model, tpn, cfg.test_time(), name), \
        {"base": base_params, "tpn": tpn_params}, nav_cfg, cfg


def default_batch_size(base_params, scope: str, budget_bytes: float = 5e8) -> int:
    """Episodes per evaluation batch so that the fast weights (with their update and
    gradient copies) stay within budget_bytes: 1000 for the actor head, fewer for the
    trunk or all parameters."""
    per_env = 3 * 4 * scope_size(base_params, scope)
    return int(max(16, min(1000, budget_bytes // per_env)))


def init_tpn_params(tpn: TPN, nav_cfg, key):
    """TPN variables from dummy inputs (one episode of one step)."""
    H = nav_cfg.hidden
    return tpn.init(key, jnp.zeros((1, 1, H)), jnp.zeros((1, 1, NUM_ACTIONS)),
                    jnp.ones((1, 1), bool))
