"""Trained models as evaluation Policies (greedy actions), and loading them from a run."""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import jax.numpy as jnp

from orgnav_jax.evaluation import Policy
from orgnav_jax.models import build_model, init_params, model_inputs, reset_carry
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.config import TrainConfig, load_config


@functools.cache
def model_policy(model, name: str = "Model") -> Policy:
    """Greedy (argmax) actions of a NavModel; the LSTM carry resets at episode starts.
    policy_params are the model's variables."""
    def init(batch, params):
        return model.initial_carry(batch)

    def act(params, carry, obs, key, scenes, fresh):
        carry = reset_carry(carry, fresh)
        logits, _, carry, _ = model.apply(params, model_inputs(scenes, obs), carry)
        return jnp.argmax(logits, -1).astype(jnp.int32), carry

    return Policy(name, init, act)


def scenes_for(cfg: TrainConfig):
    """The full SceneSet a config trains on (cached preset or a saved directory; the last
    one loaded stays in memory)."""
    from orgnav_jax.scenes import load_scenes
    return load_scenes(cfg.scene_preset, cfg.scene_seed, cfg.scenes_dir)


def load_run_model(run_dir: str | Path, best: bool = True):
    """-> (NavModel, params, config) of a training run (its best-on-val checkpoint, else
    the latest)."""
    cfg = load_config(run_dir)
    train = scenes_for(cfg).split_view("train")
    model = build_model(cfg, train)
    like = init_params(model, jax.random.PRNGKey(0), train)
    ckpt = RunCheckpoints(run_dir)
    if best and ckpt.best.latest_step() is not None:
        params, _ = ckpt.restore(like, best=True)
    else:
        from orgnav_jax.training.update import init_runner, make_optimizer
        runner_like = jax.eval_shape(lambda: init_runner(
            cfg, model, make_optimizer(cfg), train.to_device(), jax.random.PRNGKey(0)))
        runner, _ = ckpt.restore(runner_like)
        params = runner.params
    return model, params, cfg


def load_run_policy(run_dir: str | Path, best: bool = True):
    """-> (Policy, params, config) of a training run (see load_run_model)."""
    model, params, cfg = load_run_model(run_dir, best)
    return model_policy(model, cfg.model), params, cfg
