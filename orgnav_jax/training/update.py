"""One jitted chunk of training: `updates_per_chunk` x (rollout + gradient step).

    init_runner(cfg, model, optimizer, scenes, key) -> RunnerState
    train_chunk(runner, scenes)               -> (RunnerState, metrics dict of scalars)
where train_chunk = make_train_chunk(cfg, model, optimizer), jitted once.

make_train_chunk(..., mesh=mesh) pins the runner's shardings (env axis over the mesh's
"data" axis, the rest replicated: training/scale.py) at every update; population=True
vmaps the chunk over a leading seed axis of the runner (several seeds in one program:
metrics then have that axis too). With neither, the program is the plain one-device one.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import optax

from orgnav_jax import env
from orgnav_jax.models import init_params
from orgnav_jax.models.vtnet import visual_mask
from orgnav_jax.training.config import TrainConfig
from orgnav_jax.training.losses import a2c_loss, gae
from orgnav_jax.training.scale import constrain
from orgnav_jax.training.rollout import EpisodeStats, RunnerState, rollout


def env_params(cfg: TrainConfig) -> env.EnvParams:
    return env.EnvParams(success_reward=cfg.success_reward, step_penalty=cfg.step_penalty,
                         step_caps=(cfg.episode_cap,) * 4)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    """Adam with global-norm clipping (optim "ours"); optim "release": AMSGrad (the
    release's SharedAdam), and for SAVN rows no clipping (SAVN's release clips nothing;
    max_grad_norm is then unused). docs/training.md. A run that starts from a VTNet
    pre-training (cfg.pretrained) steps the pre-trained parameters at pretrained_lr_scale
    x lr (the release's two parameter groups: an Adam step scaled is Adam at that lr)."""
    if cfg.optim == "release":
        adam = optax.amsgrad(cfg.lr, eps=cfg.adam_eps)
        opt = adam if cfg.savn else optax.chain(
            optax.clip_by_global_norm(cfg.max_grad_norm), adam)
    else:
        opt = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                          optax.adam(cfg.lr, eps=cfg.adam_eps))
    if getattr(cfg, "pretrained", None) is not None and cfg.pretrained_lr_scale != 1.0:
        opt = optax.chain(opt, optax.masked(optax.scale(cfg.pretrained_lr_scale),
                                            visual_mask))
    return opt


def init_runner(cfg: TrainConfig, model, optimizer, scenes, key) -> RunnerState:
    """A fresh RunnerState: parameters, Adam moments, cfg.num_envs reset environments.
    (The resets are one jitted program per env count and EnvParams, like init_params:
    op by op they compiled every primitive on a process's first call.)"""
    k_params, k_env, k_run = jax.random.split(key, 3)
    params = init_params(model, k_params, scenes)
    env_state = _reset_all(jax.random.split(k_env, cfg.num_envs), scenes, env_params(cfg))
    return RunnerState(params=params, opt_state=optimizer.init(params), env_state=env_state,
                       carry=model.initial_carry(cfg.num_envs),
                       fresh=jnp.ones(cfg.num_envs, bool),
                       ep_return=jnp.zeros(cfg.num_envs, jnp.float32), key=k_run,
                       update=jnp.int32(0))


@partial(jax.jit, static_argnums=2)
def _reset_all(keys, scenes, params: env.EnvParams):
    """(N, 2) keys -> the EnvState of N reset environments."""
    return jax.vmap(env.reset, in_axes=(0, None, None))(keys, scenes, params)[1]


def make_train_chunk(cfg: TrainConfig, model, optimizer, mesh=None, population=False):
    """A jitted (runner, scenes) -> (runner, metrics) doing cfg.updates_per_chunk updates
    (sharded over `mesh`; vmapped over a leading seed axis if `population`)."""
    params_env = env_params(cfg)
    grad_fn = jax.value_and_grad(a2c_loss, has_aux=True)

    def train_chunk(runner: RunnerState, scenes):
        def one_update(carry, _):
            runner, stats = carry
            runner = constrain(runner, mesh)
            carry0 = runner.carry
            runner, traj, last_value, ep = rollout(model, runner, scenes, params_env,
                                                   cfg.rollout_len, cfg.dropout)
            adv, ret = gae(traj.reward, traj.value, traj.done, last_value, cfg.gamma,
                           cfg.gae_lambda)
            (loss, aux), grads = grad_fn(runner.params, model, scenes, traj, carry0, adv,
                                         ret, cfg, batch_major=mesh is not None)
            updates, opt_state = optimizer.update(grads, runner.opt_state, runner.params)
            params = optax.apply_updates(runner.params, updates)
            runner = constrain(runner.replace(params=params, opt_state=opt_state,
                                              update=runner.update + 1), mesh)
            stats = jax.tree_util.tree_map(jnp.add, stats, ep)
            return (runner, stats), dict(aux, loss=loss, grad_norm=optax.tree.norm(grads))

        (runner, stats), aux = jax.lax.scan(one_update, (runner, EpisodeStats.zeros()), None,
                                            length=cfg.updates_per_chunk)
        metrics = {k: v.mean() for k, v in aux.items()}
        metrics["loss_finite"] = jnp.isfinite(aux["loss"]).all()
        metrics.update(episodes=stats.count, success=stats.success, spl=stats.spl,
                       ret=stats.ret, length=stats.length)
        return runner, metrics

    return jax.jit(jax.vmap(train_chunk, in_axes=(0, None)) if population else train_chunk)
