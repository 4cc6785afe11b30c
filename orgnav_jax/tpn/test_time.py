"""The navigation policy with TPN's test-time update, as an evaluation Policy.

At every step of every episode (vmapped over environments, inside the jitted evaluation
scan): the base model runs with the episode's own fast weights; the TPN reads its
internal memory; on a deadlock step (or every step, when="all") the target is the TPN's
argmax (or a random action, target="random"), the fast weights take one SGD step of
CE(policy logits, target), and the agent acts greedily with the updated weights. Fast
weights are reset to the trained parameters at each episode start and before steps
reset_every, 2 reset_every, ... of it (the release's 50; 0: never within an episode).

cfg.placement "release" (the ECCV release's agents/agent.py:149-188 and
runners/train_util.py:9-37): step t acts with its logits as they are; their update
(CE(policy logits of step t, the TPN's argmax of step t)) is kept pending, and step t+1
applies it first if s_{t+1} is a deadlock (or always, when="all"); step t is not re-run.
"state" (ours, the default): the update is on the deadlock state's own logits and the
step is re-run with the new weights.

The fast weights of `scope` (default "all", the release's: every parameter of the
navigation network) are low-rank deltas of the LSTM kernels plus dense copies of the
rest (tpn/lowrank.py); the actor head alone keeps a dense copy and runs the model up to
the LSTM once, shared (tpn/fast_weights.py, also the reference the low-rank form is
tested against). The gradient is truncated to the current step (the LSTM carry from the
previous step is a constant).

tpn_train_mode reproduces the release's confound: its "+TPN" evaluation ran the network
in train mode, so dropout was active there and not in "w/o TPN". With it, a fresh dropout
mask (the navigation model's rate) is drawn every step and used for the forward pass,
the update and the action; without it the evaluation is deterministic.

    policy, params, nav_cfg, tpn_cfg = load_tpn_policy("runs/baseline-calibrated/tpn")
    evaluation.evaluate(policy, params, scenes, episodes)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from orgnav_jax.compile_cache import compiled_once
from orgnav_jax.constants import DONE, NUM_ACTIONS
from orgnav_jax.env import EnvParams
from orgnav_jax.errors import choose
from orgnav_jax.evaluation import Policy
from orgnav_jax.models import dropout_mask, model_inputs, reset_carry
from orgnav_jax.models.tpn_net import (
    TPN, attention_map, memory_init, memory_record, memory_reset)
from orgnav_jax.tpn.config import (
    TestTime, TPNConfig, TPNNetwork, get_tpn_config, load_tpn_config)
from orgnav_jax.tpn.deadlock import detect, detector_init
from orgnav_jax.tpn.fast_weights import DenseFastWeights, scope_size
from orgnav_jax.tpn.lowrank import LowRankFastWeights, make_plan, plan_floats
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.runs import load_run_model


@struct.dataclass
class TPNCarry:
    """Per-environment state of the policy (leading axis B everywhere)."""
    lstm: Any           # the base model's LSTM carry
    fast: Any           # the episode's fast weights (dense copies or a LowRankState)
    memory: Any         # models.tpn_net.TPNMemory (internal memory)
    vision: Any         # the deadlock detector's memory (None for "visited")
    updates: jax.Array  # (B,) int32 test-time updates in the running episode
    steps: jax.Array    # (B,) int32 index of the step in the running episode
    read: Any           # ((B, k) weights, (B, k) slots): the TPN's last memory read


IMPLS = ("auto", "dense", "lowrank")


def build_tpn(nav_cfg, cfg: TPNNetwork) -> TPN:
    """The TPN network for a navigation config (its hidden width) and TPN settings."""
    return TPN(hidden=nav_cfg.hidden, action_embed=cfg.action_embed, top_k=cfg.top_k)


def longest_episode() -> int:
    """Steps of the longest test episode (the evaluation caps): the TPN memory's slots."""
    return max(EnvParams.evaluation().step_caps)


def update_slots(cfg: TestTime) -> int:
    """Updates an episode can take between two resets (one per step at most)."""
    longest = longest_episode()
    return min(cfg.reset_every, longest) if cfg.reset_every > 0 else longest


def fast_weights(model, cfg: TestTime, base_params, impl: str = "auto"):
    """The per-episode fast weights of cfg.scope: dense copies for the actor head (the
    model up to the LSTM runs once, shared), low-rank LSTM deltas otherwise ("auto");
    or forced ("dense": the reference, "lowrank")."""
    if impl not in IMPLS:
        raise ValueError(f"fast weights impl {impl!r}: expected one of {IMPLS}")
    if impl == "dense" or (impl == "auto" and cfg.scope == "actor"):
        return DenseFastWeights(model, cfg.scope, cfg.placement)
    return LowRankFastWeights(model, make_plan(base_params, cfg.scope, update_slots(cfg)),
                              cfg.placement)


def tpn_policy(model, tpn: TPN, cfg: TestTime, name: str = "TPN", dropout: float = 0.0,
               impl: str = "auto", box_scale: float = 1.0) -> Policy:
    """policy_params = {"base": navigation variables, "tpn": TPN variables}. `dropout`:
    the navigation model's rate, used with cfg.tpn_train_mode only. box_scale multiplies
    the boxes the model reads (the release's models read pixel boxes: models/release.py).

    Where no dropout is applied (train mode off, or a rate of 0: an all-ones mask) the
    policy is the one without train mode and rate, so those spellings share one compiled
    evaluation (compile_cache.py)."""
    if not cfg.tpn_train_mode or dropout == 0:
        cfg, dropout = dataclasses.replace(cfg, tpn_train_mode=False), 0.0
    return _tpn_policy(model, tpn, cfg, name, dropout, impl, float(box_scale))


@compiled_once
def _tpn_policy(model, tpn: TPN, cfg: TestTime, name: str, dropout: float,
                impl: str, box_scale: float = 1.0) -> Policy:
    def init(batch, params):
        fw = fast_weights(model, cfg, params["base"], impl)
        size = longest_episode()
        k = min(tpn.top_k, size)
        zeros = jnp.zeros(batch, jnp.int32)
        return TPNCarry(model.initial_carry(batch), fw.init(batch, params["base"]),
                        memory_init(batch, size, tpn.hidden), detector_init(cfg, batch, size),
                        zeros, zeros, (jnp.zeros((batch, k)), jnp.zeros((batch, k), jnp.int32)))

    def act(params, carry: TPNCarry, obs, key, scenes, fresh):
        fw = fast_weights(model, cfg, params["base"], impl)
        B = fresh.shape[0]
        steps = jnp.where(fresh, 0, carry.steps + 1)
        reset = fresh if cfg.reset_every <= 0 else fresh | (steps % cfg.reset_every == 0)
        fast = fw.reset(params["base"], carry.fast, reset)
        inputs = model_inputs(scenes, obs)
        if box_scale != 1.0:
            inputs = inputs._replace(box=inputs.box * box_scale)
        if cfg.tpn_train_mode:       # the release's "+TPN" evaluation: dropout active
            inputs = inputs._replace(drop=dropout_mask(
                jax.random.fold_in(key, 1), dropout, model.dropout_shape(B)))

        deadlock, vision = detect(cfg, carry.vision, obs.deadlock, inputs.glob, fresh)
        flagged = choose({"deadlock": deadlock, "all": jnp.ones_like(deadlock)},
                         cfg.when, "TPN update steps (when)")
        # an episode that said Done is over (the evaluation scan keeps stepping its
        # frozen last observation): no more updates, so fewer slots to read
        live = obs.prev_action[:, DONE] == 0
        release = choose({"state": False, "release": True}, cfg.placement, "TPN placement")
        # "state": this step updates where flagged; "release": every live step's update is
        # computed and kept pending, and this step first applies the previous step's
        # where this state is flagged (s_{t+1} of that step)
        commit = flagged & live & ~fresh if release else None

        def decide(logits, h):
            tpn_logits, r, memory, read = tpn.apply(params["tpn"], h,
                                              memory_reset(carry.memory, fresh),
                                              method=tpn.step_logits)
            target = choose({
                "tpn": lambda: jnp.argmax(tpn_logits, -1),
                "random": lambda: jax.random.randint(key, fresh.shape, 0, NUM_ACTIONS)},
                cfg.target, "TPN update target")()
            update = live if release else flagged & live
            return target, update, (r, memory, read)

        # the model with the episode's fast weights; updating rows take one SGD step and
        # act with the updated weights (placement "release": module docstring)
        logits, lstm, fast, (r, memory, read) = fw.step(
            params["base"], fast, inputs, reset_carry(carry.lstm, fresh), decide, cfg.tpn_lr,
            **({"commit": commit} if release else {}))
        update = commit if release else flagged & live
        memory = memory_record(memory, r, jax.nn.softmax(logits))
        updates = jnp.where(fresh, 0, carry.updates) + update.astype(jnp.int32)
        return jnp.argmax(logits, -1).astype(jnp.int32), TPNCarry(
            lstm, fast, memory, vision, updates, steps, read)

    def record(carry: TPNCarry) -> dict:
        """Per step (traces only): updates so far, and the read's weight on each memory
        slot (B, M) (slot i: step i -> i+1 of the episode)."""
        return {"tpn_updates": carry.updates,
                "tpn_attention": attention_map(carry.read, longest_episode())}

    return Policy(name, init, act, record=record)


def load_tpn_policy(run_dir: str | Path, **test_time):
    """-> (Policy, {"base", "tpn"} params, navigation config, TPN config) of a stage-2
    run (its best-on-val TPN and its base's best-on-val model); `test_time` overrides
    test-time fields (config.TEST_TIME_FIELDS: tpn_lr, scope, when, target, deadlock,
    cosine_threshold, reset_every, tpn_train_mode)."""
    cfg = load_tpn_config(run_dir)
    cfg = get_tpn_config(**{**dataclasses.asdict(cfg), **test_time})
    model, base_params, nav_cfg = load_run_model(cfg.base_dir)
    tpn = build_tpn(nav_cfg, cfg.network)
    like = init_tpn_params(tpn, nav_cfg, jax.random.PRNGKey(0))
    ckpt = RunCheckpoints(run_dir)
    if ckpt.best.latest_step() is None:
        raise FileNotFoundError(f"{run_dir}: no best-on-val TPN checkpoint yet")
    tpn_params, _ = ckpt.restore(like, best=True)
    name = tpn_name(nav_cfg.model, cfg)
    return tpn_policy(model, tpn, cfg.test_time(), name,
                      float(getattr(nav_cfg, "dropout", 0.0))), \
        {"base": base_params, "tpn": tpn_params}, nav_cfg, cfg


def tpn_name(base: str, cfg: TestTime | TPNConfig) -> str:
    """The test-time policy's name: base+TPN and the settings that differ from the
    paper's ("-train": dropout on, the release's confound)."""
    return f"{base}+TPN" + ("" if cfg.when == "deadlock" else f"-{cfg.when}") + \
        ("" if cfg.target == "tpn" else f"-{cfg.target}") + \
        ("-train" if cfg.tpn_train_mode else "") + \
        ("-state-placement" if cfg.placement == "state" else "")


def default_batch_size(base_params, cfg: TestTime | TPNConfig | str, impl: str = "auto",
                       budget_bytes: float = 4e9) -> int:
    """Episodes per evaluation batch (16 to 1000) so that the fast weights, with their
    gradient and update copies, stay within budget_bytes. `cfg`: the TPNConfig, or just a
    scope (then the slots of reset_every=0, the most an episode can need). At the paper's
    widths, all parameters: 1000 with reset_every 50, 400 with 0 (full copies: 44)."""
    if isinstance(cfg, str):
        cfg = TestTime(scope=cfg, reset_every=0)
    if impl == "dense" or (impl == "auto" and cfg.scope == "actor"):
        floats = 3 * scope_size(base_params, cfg.scope)
    else:
        dense, slots = plan_floats(base_params, make_plan(base_params, cfg.scope,
                                                          update_slots(cfg)))
        floats = 3 * dense + 2 * slots
    return int(max(16, min(1000, budget_bytes // (4 * floats))))


def init_tpn_params(tpn: TPN, nav_cfg, key):
    """TPN variables from dummy inputs (one episode of one step)."""
    H = nav_cfg.hidden
    return tpn.init(key, jnp.zeros((1, 1, H)), jnp.zeros((1, 1, NUM_ACTIONS)),
                    jnp.ones((1, 1), bool))
