"""Stage 2: train the TPN on deadlock steps of a frozen navigation model.

Each update, the frozen base acts in `num_envs` fresh training episodes of up to
`episode_cap` steps (no auto-reset, so each row of the batch is one whole episode and the
TPN's internal memory is exact); the TPN reads that episode's past steps and is trained
with CE(TPN logits, expert action) on the deadlock steps. The base never changes, so the
collected data do not depend on the TPN's parameters.

Which steps and which label (cfg.placement): "state" (ours), the steps taken at a
deadlock state, labelled with the expert action there; "release" (the ECCV release's
agents/agent.py:192-205), the steps whose action led into a deadlock (s_{t+1} visited
before in the episode, which includes every failed move and every Done), labelled with
the expert action read after the move, at s_{t+1}. The TPN's logits are those of step t
either way. cfg.optim "release": the CE summed over an episode's steps (mean over
episodes), AMSGrad (eps 1e-3): the release's A3C optimiser.

    collect(model, base_params, cfg, scenes, key, num)    -> EpisodeBatch (N, T, ...)
    tpn_loss(tpn_params, tpn, batch)                      -> (CE, aux)
    train_tpn(cfg)                                        -> summary (run_dir/checkpoints)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import optax
from flax import struct

from orgnav_jax import env
from orgnav_jax.compile_cache import compiled_once, computation_of
from orgnav_jax.constants import DONE
from orgnav_jax.errors import choose
from orgnav_jax.models import model_inputs
from orgnav_jax.tpn.config import TPNConfig, check_tpn_base, load_tpn_config
from orgnav_jax.tpn.deadlock import detect, detector_init
from orgnav_jax.tpn.test_time import build_tpn, init_tpn_params
from orgnav_jax.training.config import TrainConfig, load_config
from orgnav_jax.training.config_fields import host_only_fields
from orgnav_jax.training.driver import Stage, run_stage
from orgnav_jax.training.losses import imitation_loss
from orgnav_jax.training.memory import check_tpn_memory
from orgnav_jax.training.run_dir import open_run_dir
from orgnav_jax.training.runs import (
    check_training_scenes, device_splits, load_run_model, scenes_for)
from orgnav_jax.tree import where_rows


@struct.dataclass
class EpisodeBatch:
    """N whole episodes of the frozen base, batch-major (N, T, ...)."""
    h: jax.Array          # (N, T, hidden) LSTM outputs
    probs: jax.Array      # (N, T, 6) the base's action distribution
    valid: jax.Array      # (N, T) bool: the episode is still running at step t
    deadlock: jax.Array   # (N, T) bool: step t is supervised (module docstring: the
                          # external memory flags s_t, or the step led into a deadlock)
    expert: jax.Array     # (N, T) int32 its label: the expert action at s_t, or at
                          # s_{t+1} (placement "release"); NO_ACTION = -1 where none
    success: jax.Array    # (N,) bool: the base reached the target


@struct.dataclass
class TPNRunner:
    params: Any
    opt_state: Any
    key: jax.Array
    update: jax.Array


def collect(model, base_params, cfg: TPNConfig, scenes, key, num: int) -> EpisodeBatch:
    """The frozen base acts (sampled or greedy, cfg.act) in `num` random episodes of
    `scenes` for cfg.episode_cap steps; finished episodes stay frozen (valid False)."""
    params = env.EnvParams(step_caps=(cfg.episode_cap,) * 4)
    k_reset, k_act = jax.random.split(key)
    _, state = jax.vmap(env.reset, in_axes=(0, None, None))(
        jax.random.split(k_reset, num), scenes, params)
    v_step = jax.vmap(env.step_env, in_axes=(0, 0, None, None))
    v_observe = jax.vmap(env.observe, in_axes=(0, None))

    def body(carry, k):
        state, lstm, running, success, vision, fresh = carry
        obs = v_observe(state, scenes)
        inputs = model_inputs(scenes, obs)
        logits, _, lstm, h = model.apply(base_params, inputs, lstm)
        action = choose({"sample": lambda: jax.random.categorical(k, logits),
                         "greedy": lambda: jnp.argmax(logits, -1)},
                        cfg.act, "stage-2 action rule (act)")().astype(jnp.int32)
        deadlock, vision = detect(cfg.memory, vision, obs.deadlock, inputs.glob, fresh)
        expert = scenes.expert_action[state.state, state.target]
        _, state2, _, done, info = v_step(state, action, scenes, params)
        if cfg.placement == "release":   # the step that led into a deadlock, the label at s_{t+1}
            deadlock = info["failed"] | info["revisited"] | (action == DONE)
            expert = scenes.expert_action[state2.state, state2.target]
        state = where_rows(running, state2, state)
        out = (jax.lax.stop_gradient(h), jax.lax.stop_gradient(jax.nn.softmax(logits)),
               running, deadlock, expert.astype(jnp.int32))      # the base is frozen
        success = success | (running & info["success"])
        return (state, lstm, running & ~done, success, vision, jnp.zeros_like(fresh)), out

    init = (state, model.initial_carry(num), jnp.ones(num, bool), jnp.zeros(num, bool),
            detector_init(cfg.memory, num, cfg.episode_cap), jnp.ones(num, bool))
    (_, _, _, success, _, _), (h, probs, valid, deadlock, expert) = jax.lax.scan(
        body, init, jax.random.split(k_act, cfg.episode_cap))
    batch_major = lambda x: jnp.swapaxes(x, 0, 1)
    return EpisodeBatch(batch_major(h), batch_major(probs), batch_major(valid),
                        batch_major(deadlock), batch_major(expert), success)


def tpn_loss(params, tpn, batch: EpisodeBatch, optim: str = "ours"):
    """Mean CE(TPN logits, expert action) over valid deadlock steps -> (loss, aux with
    accuracy (argmax == expert) and the number of such steps). optim "release": the loss
    is the CE summed over each episode's steps, mean over episodes (aux's ce stays the
    mean over steps)."""
    logits = tpn.apply(params, batch.h, batch.probs, batch.valid)
    mask = (batch.valid & batch.deadlock).astype(jnp.float32)
    ce, steps = imitation_loss(logits, batch.expert, mask)
    loss = choose({"ours": lambda: ce,
                   "release": lambda: imitation_loss(logits, batch.expert, mask, "per_step")[0]
                   * mask.shape[1]}, optim, "stage-2 optimiser (optim)")()
    hit = (jnp.argmax(logits, -1) == batch.expert) * mask * (batch.expert >= 0)
    return loss, {"ce": ce, "accuracy": hit.sum() / jnp.maximum(steps, 1.0),
                "deadlock_steps": steps, "base_success": batch.success.mean()}


def make_optimizer(cfg: TPNConfig):
    adam = choose({"ours": lambda: optax.adam(cfg.lr),
                   "release": lambda: optax.amsgrad(cfg.lr, eps=1e-3)},
                  cfg.optim, "stage-2 optimiser (optim)")()
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), adam)


def make_tpn_chunk(cfg: TPNConfig, model, tpn, optimizer):
    """A jitted (runner, base_params, scenes) -> (runner, metrics) of
    cfg.updates_per_chunk stage-2 updates."""
    grad_fn = jax.value_and_grad(tpn_loss, has_aux=True)

    @jax.jit
    def chunk(runner: TPNRunner, base_params, scenes):
        def one(runner, _):
            key, k = jax.random.split(runner.key)
            batch = collect(model, base_params, cfg, scenes, k, cfg.num_envs)
            (loss, aux), grads = grad_fn(runner.params, tpn, batch, cfg.optim)
            updates, opt_state = optimizer.update(grads, runner.opt_state, runner.params)
            runner = TPNRunner(optax.apply_updates(runner.params, updates), opt_state, key,
                               runner.update + 1)
            return runner, dict(aux, loss=loss)

        runner, aux = jax.lax.scan(one, runner, None, length=cfg.updates_per_chunk)
        metrics = {k: v.mean() for k, v in aux.items()}
        metrics["loss_finite"] = jnp.isfinite(aux["loss"]).all()
        return runner, metrics

    return chunk


# The fields stage 2's programs do not read (the host loop's bookkeeping and the
# test-time update's fields), marked host_only next to each field (tpn/config.py): runs
# that differ only in them share one compiled chunk, val collection and val loss
# (compile_cache.py).
HOST_ONLY_FIELDS = host_only_fields(TPNConfig, "tpn")


def preflight_tpn(cfg: TPNConfig, nav_cfg: TrainConfig):
    """Every check before stage 2 writes or compiles anything -> the base run's SceneSet:
    the TPN config's own validation, the base (not SAVN), its scenes' train and val rooms
    and one chunk's memory estimate (training.memory.check_tpn_memory)."""
    cfg.validate()
    check_tpn_base(nav_cfg, cfg.base_dir)
    scenes = scenes_for(nav_cfg)
    check_training_scenes(scenes, nav_cfg)
    check_tpn_memory(cfg, nav_cfg, scenes)
    return scenes


@compiled_once
def cached_programs(cfg: TPNConfig, model, tpn):
    """(optimizer, chunk, collect_val, val_metrics) of a stage-2 computation, jitted once
    per process for equal (cfg without HOST_ONLY_FIELDS, model, tpn):
    collect_val(base_params, scenes, key, num) -> EpisodeBatch (num static);
    val_metrics(tpn_params, batch) -> tpn_loss's aux."""
    optimizer = make_optimizer(cfg)
    collect_val = jax.jit(lambda base_params, scenes, key, num: collect(
        model, base_params, cfg, scenes, key, num), static_argnums=3)
    val_metrics = jax.jit(lambda params, batch: tpn_loss(params, tpn, batch)[1])
    return optimizer, make_tpn_chunk(cfg, model, tpn, optimizer), collect_val, val_metrics


def train_tpn(cfg: TPNConfig, resume: bool = False, progress: bool = True,
              stop_after_chunks: int | None = None) -> dict:
    """Train (or resume) the TPN of cfg.run_dir on its frozen base -> summary dict.
    The best-on-val TPN (accuracy on the val episodes' deadlock steps) is kept."""
    # config ranges, scenes, memory, then the base's checkpoint: before anything is written
    scenes = preflight_tpn(cfg, load_config(cfg.base_dir))
    model, base_params, nav_cfg = load_run_model(cfg.base_dir)
    with open_run_dir(cfg.run_dir, cfg, resume, load_tpn_config) as run_dir:
        return _train_tpn(cfg, run_dir, model, base_params, nav_cfg, scenes, resume,
                          progress, stop_after_chunks)


def _train_tpn(cfg: TPNConfig, run_dir: Path, model, base_params, nav_cfg, scenes,
               resume: bool, progress: bool, stop_after_chunks: int | None) -> dict:
    train_scenes, val_scenes = device_splits(scenes, "train", "val")   # preflight's set
    tpn = build_tpn(nav_cfg, cfg.network)
    optimizer, chunk_fn, collect_val, val_metrics = cached_programs(
        computation_of(cfg, HOST_ONLY_FIELDS), model, tpn)
    k_init, k_run = jax.random.split(jax.random.PRNGKey(cfg.seed))
    params = init_tpn_params(tpn, nav_cfg, k_init)
    # committed to the device like the chunk's outputs, so the first chunk and the rest
    # are one compiled program (uncommitted inputs compiled it a second time)
    runner = jax.device_put(TPNRunner(params, optimizer.init(params), k_run, jnp.int32(0)),
                            jax.local_devices()[0])
    # the base is frozen: the val episodes are collected once (same for every seed)
    val_batch = collect_val(base_params, val_scenes, jax.random.PRNGKey(2 ** 20),
                            4 * cfg.eval_episodes_per_room_type)
    val_fn = lambda p: val_metrics(p, val_batch)
    floats = lambda m: {k: float(v) for k, v in jax.device_get(m).items()}
    stage = Stage(
        name="train TPN", unit="ep", step_name="episodes", rate_key="episodes_per_s",
        per_chunk=cfg.updates_per_chunk * cfg.num_envs, total=cfg.num_updates * cfg.num_envs,
        chunk=lambda runner: chunk_fn(runner, base_params, train_scenes), summarize=floats,
        validate=lambda runner: floats(val_fn(runner.params)),
        score_keys=("accuracy",), best_keys=("accuracy", "ce"), progress_keys=("accuracy",))
    return run_stage(stage, runner, cfg, run_dir, resume, progress, stop_after_chunks)
