"""VTNet's pre-training (issue 43): the visual transformer learns the expert's action
before A2C, as a stage of the shared driver (training/driver.py).

    summary = pretrain(PretrainConfig.of(get_config("vtnet", run_dir="runs/vtnet-pretrain")))
    params = load_pretrained(cfg, params)           # the A2C stage starts from it

The release (main_pretraining.py, runners/pretrain_engine.py, utils/pretrain_util.py,
models/pretrainedvisualtransformer.py) trains its PreTrainedVisualTransformer, the
navigation model's visual part plus a linear head (49 x 64 -> 6, `pretrain_fc`), with
cross-entropy against the optimal action of (state, target) annotations, AdamW (lr 1e-4,
weight decay 1e-4), the gradient norm clipped to 0.1, batches of 128, the lr x0.1 every
10 epochs; val accuracy (argmax == optimal action) after each epoch. main.py then loads
every parameter whose name and shape the navigation model shares, and trains those at
pretrained_lr (1e-5) and the rest at lr (1e-4).

Here (models/vtnet.py: VTNetPretrain): each update draws pretrain_batch (scene, state,
target) triples of the training rooms inside jit (env.sample_episode with no minimum start
distance: a room uniformly, a state of it uniformly, a valid target of the room
uniformly), labels them with the scene set's expert_action table and takes one AdamW step
on the mean cross-entropy (optax.adamw: decoupled weight decay on every parameter, as
torch's AdamW). No previous action enters (the release's pre-training network has none).
Val: a fixed seeded draw of pretrain_val_samples triples of the val rooms (the same for
every run) -> accuracy and mean cross-entropy, in metrics.jsonl; the best-on-val
parameters are kept (best/), and the A2C stage starts from them (load_pretrained).
The budget counts samples (pretrain_samples), the unit of the progress bar and the log's
step ("samples").

A pre-training run's directory holds a PretrainConfig (training/config.py): the VTNet's
TrainConfig saved with stage "pretrain", so neither kind of run is mistaken for the other.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from orgnav_jax import env
from orgnav_jax.compile_cache import compiled_once, computation_of
from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS
from orgnav_jax.errors import UserError
from orgnav_jax.models import build_model, dropout_mask, model_inputs
from orgnav_jax.models.vtnet import VTNetPretrain, is_visual, pretrain_init
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.config import (  # noqa: F401  (PretrainConfig re-exported)
    PretrainConfig, TrainConfig, load_pretrain_config)
from orgnav_jax.training.config_fields import host_only_fields
from orgnav_jax.training.driver import Stage, run_stage
from orgnav_jax.training.losses import imitation_loss
from orgnav_jax.training.run_dir import open_run_dir
from orgnav_jax.training.runs import check_pretrained, checked_scenes, device_splits

VAL_KEY = 2 ** 20 + 43        # the val draw's key: the same triples for every run


@struct.dataclass
class PretrainRunner:
    params: Any
    opt_state: Any
    key: jax.Array
    update: jax.Array


def pretrain_network(cfg: TrainConfig, scenes) -> VTNetPretrain:
    """The pre-training network of cfg's VTNet (its encoder and trunk, with their names)."""
    model = build_model(cfg, scenes)
    return VTNetPretrain(model.encoder, model.trunk)


def sample_batch(scenes, key: jax.Array, num: int):
    """num random (state, target) pairs of `scenes` -> (ModelInputs with no previous
    action, expert actions (num,) int32): a room uniformly, a state of it uniformly, a
    valid target uniformly (env.sample_episode with min_start_dist 0)."""
    params = env.EnvParams(min_start_dist=0)
    k_sample, _ = jax.random.split(key)
    scene, start, target = jax.vmap(env.sample_episode, in_axes=(0, None, None))(
        jax.random.split(k_sample, num), scenes, params)
    state = jax.vmap(env.start_episode, in_axes=(0, 0, 0, None, None))(
        scene, start, target, scenes, params)
    inputs = model_inputs(scenes, jax.vmap(env.observe, in_axes=(0, None))(state, scenes))
    inputs = inputs._replace(prev_action=jnp.zeros((num, NUM_ACTIONS), jnp.float32))
    return inputs, scenes.expert_action[state.state, state.target].astype(jnp.int32)


def pretrain_loss(params, net: VTNetPretrain, inputs, labels):
    """Mean cross-entropy of the expert actions -> (loss, {"ce", "accuracy"})."""
    logits = net.apply(params, inputs)
    valid = (labels >= 0).astype(jnp.float32)
    ce, count = imitation_loss(logits, labels, valid)
    hit = (jnp.argmax(logits, -1) == labels) * valid
    return ce, {"ce": ce, "accuracy": hit.sum() / jnp.maximum(count, 1.0)}


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    """The release's: AdamW (torch's defaults but lr and weight decay), the gradient norm
    clipped to pretrain_clip, the lr x0.1 every pretrain_lr_drop samples (StepLR)."""
    lr = cfg.pretrain_lr
    if cfg.pretrain_lr_drop:
        every = max(1, cfg.pretrain_lr_drop // cfg.pretrain_batch)
        lr = optax.exponential_decay(cfg.pretrain_lr, every, 0.1, staircase=True)
    return optax.chain(optax.clip_by_global_norm(cfg.pretrain_clip),
                       optax.adamw(lr, b1=0.9, b2=0.999, eps=1e-8,
                                   weight_decay=cfg.pretrain_weight_decay))


# fields pre-training's programs do not read (compile_cache.py): marked host_only next to
# each field (training/config.py)
HOST_ONLY_FIELDS = host_only_fields(TrainConfig, "pretrain")


@compiled_once
def cached_programs(cfg: TrainConfig, net: VTNetPretrain):
    """(optimizer, init, chunk, val) of a pre-training computation, jitted once per
    process: init(key, scenes) -> params; chunk(runner, scenes) -> (runner, metrics)
    (cfg.updates_per_chunk updates); val(params, inputs, labels) -> {"ce", "accuracy"}
    over batches of pretrain_batch (lax.map: bounded memory at paper widths)."""
    optimizer = make_optimizer(cfg)
    grad_fn = jax.value_and_grad(pretrain_loss, has_aux=True)
    B = cfg.pretrain_batch

    @jax.jit
    def init(key, scenes):
        inputs, _ = sample_batch(scenes, key, 1)
        return pretrain_init(net.init({"params": key}, inputs), jax.random.fold_in(key, 1))

    @jax.jit
    def chunk(runner: PretrainRunner, scenes):
        def one(runner, _):
            key, k_batch, k_drop = jax.random.split(runner.key, 3)
            inputs, labels = sample_batch(scenes, k_batch, B)
            if cfg.dropout:          # the release's Dropout(dropout_rate) per cell
                inputs = inputs._replace(drop=dropout_mask(
                    k_drop, cfg.dropout, (B, FEATURE_GRID, FEATURE_GRID, net.trunk.dropout_channels())))
            (loss, aux), grads = grad_fn(runner.params, net, inputs, labels)
            updates, opt_state = optimizer.update(grads, runner.opt_state, runner.params)
            runner = PretrainRunner(optax.apply_updates(runner.params, updates), opt_state,
                                    key, runner.update + 1)
            return runner, dict(aux, loss=loss, grad_norm=optax.tree.norm(grads))

        runner, aux = jax.lax.scan(one, runner, None, length=cfg.updates_per_chunk)
        metrics = {k: v.mean() for k, v in aux.items()}
        metrics["loss_finite"] = jnp.isfinite(aux["loss"]).all()
        return runner, metrics

    @jax.jit
    def val(params, inputs, labels):
        batches = jax.tree_util.tree_map(
            lambda x: x.reshape((-1, B) + x.shape[1:]), (inputs, labels))
        logits = jax.lax.map(lambda b: net.apply(params, b[0]), batches)
        logits = logits.reshape((-1, NUM_ACTIONS))
        valid = (labels >= 0).astype(jnp.float32)
        ce, count = imitation_loss(logits, labels, valid)
        hit = (jnp.argmax(logits, -1) == labels) * valid
        return {"ce": ce, "accuracy": hit.sum() / jnp.maximum(count, 1.0)}

    return optimizer, init, chunk, val


def val_set(cfg: TrainConfig, val_scenes):
    """The fixed val draw: pretrain_val_samples rounded up to whole batches."""
    num = math.ceil(cfg.pretrain_val_samples / cfg.pretrain_batch) * cfg.pretrain_batch
    return jax.jit(sample_batch, static_argnums=2)(val_scenes, jax.random.PRNGKey(VAL_KEY),
                                                   num)


def dataset_pairs(scenes) -> int:
    """The (state, valid target) pairs of a scene set: the release's dataset size, for
    reading its epochs as samples (docs/vtnet.md)."""
    count = np.asarray(scenes.state_count, np.int64)
    return int((count * np.asarray(scenes.targets).sum(1)).sum())


def pretrain(cfg: PretrainConfig, resume: bool = False, progress: bool = True,
             stop_after_chunks: int | None = None) -> dict:
    """Pre-train (or resume) VTNet's visual transformer in cfg.run_dir -> summary (best
    val accuracy and cross-entropy, samples, compile and wall time)."""
    cfg.validate()
    scenes = checked_scenes(cfg, resumed=[cfg.run_dir] if resume else [])
    with open_run_dir(cfg.run_dir, cfg, resume, load_pretrain_config) as run_dir:
        train_scenes, val_scenes = device_splits(scenes, "train", "val")
        net = pretrain_network(cfg, train_scenes)
        optimizer, init, chunk, val = cached_programs(
            computation_of(cfg, HOST_ONLY_FIELDS), net)
        k_init, k_run = jax.random.split(jax.random.PRNGKey(cfg.seed))
        params = init(k_init, train_scenes)
        runner = jax.device_put(PretrainRunner(params, optimizer.init(params), k_run,
                                               jnp.int32(0)), jax.local_devices()[0])
        val_inputs, val_labels = val_set(cfg, val_scenes)
        floats = lambda m: {k: float(v) for k, v in jax.device_get(m).items()}
        stage = Stage(
            name="pretrain vtnet", unit="sample", step_name="samples",
            rate_key="samples_per_s", per_chunk=cfg.updates_per_chunk * cfg.pretrain_batch,
            total=cfg.total_samples,
            chunk=lambda r: chunk(r, train_scenes), summarize=floats,
            validate=lambda r: floats(val(r.params, val_inputs, val_labels)),
            score_keys=("accuracy",), best_keys=("accuracy", "ce"),
            progress_keys=("accuracy",))
        return run_stage(stage, runner, cfg, run_dir, resume, progress, stop_after_chunks)


def load_pretrained(cfg: TrainConfig, params):
    """params (a VTNet's variables) with the visual parameters (models/vtnet.py:
    VISUAL_MODULES) of the pre-training run cfg.pretrained (its best-on-val checkpoint)
    -> the new tree (check_pretrained has checked the run)."""
    check_pretrained(cfg)
    like = jax.eval_shape(lambda: _params_like(load_pretrain_config(cfg.pretrained), params))
    saved, _ = RunCheckpoints(cfg.pretrained).restore(like, best=True)
    out, missing = _copy_visual(saved, params)
    if missing:
        raise UserError(f"--pretrained {cfg.pretrained}: {missing}")
    return out


def _params_like(pre_cfg: TrainConfig, nav_params):
    """The pre-training network's variables as the checkpoint holds them: the navigation
    model's visual arrays (their shapes) plus pretrain_fc (shapes only, under eval_shape)."""
    inner = nav_params["params"]
    visual = {}
    for path, x in jax.tree_util.tree_leaves_with_path(inner):
        name = "/".join(str(getattr(p, "key", p)) for p in path)
        if is_visual(name):
            node = visual
            keys = [str(getattr(p, "key", p)) for p in path]
            for k in keys[:-1]:
                node = node.setdefault(k, {})
            node[keys[-1]] = jnp.zeros(x.shape, x.dtype)
    rows = pre_cfg.fuse_channels * FEATURE_GRID * FEATURE_GRID
    visual["pretrain_fc"] = {"kernel": jnp.zeros((rows, NUM_ACTIONS)),
                             "bias": jnp.zeros((NUM_ACTIONS,))}
    return {"params": visual}


def _copy_visual(saved, params):
    """-> (params with every visual leaf taken from `saved`, '' or what does not fit)."""
    have = {"/".join(str(getattr(p, "key", p)) for p in path): x
            for path, x in jax.tree_util.tree_leaves_with_path(saved["params"])}
    missing = []

    def take(path, x):
        name = "/".join(str(getattr(p, "key", p)) for p in path)
        if not is_visual(name):
            return x
        if name not in have:
            missing.append(name)
            return x
        if have[name].shape != x.shape:
            missing.append(f"{name} {have[name].shape} (this model: {x.shape})")
            return x
        return jnp.asarray(have[name], x.dtype)

    out = {"params": jax.tree_util.tree_map_with_path(take, params["params"])}
    what = (f"its parameters do not fit this model ({', '.join(missing[:3])}): pre-train "
            "with the same VTNet widths") if missing else ""
    return out, what
