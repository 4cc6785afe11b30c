"""PPO with a GRU on the gymnax environment (orgnav_jax.gymnax_env), PureJaxRL style:
one file, the whole training loop (rollouts, GAE, epochs of minibatch updates) under one
jax.jit, the environment a plain gymnax Environment behind gymnax's LogWrapper.

    python examples/ppo_gymnax.py                      # the tiny rooms, about a minute
    python examples/ppo_gymnax.py --scenes small --total-timesteps 2000000

It prints the success rate of the trained policy and of a random one on the val rooms.
From Python: `params, metrics = train(config)`, then `evaluate(params, config, ...)`.
The agent reads the flat decoded observation (global feature map, detections, target and
previous action); it is a generic recurrent agent, not the paper's Baseline model.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
from gymnax.wrappers import LogWrapper

from orgnav_jax import gymnax_env
from orgnav_jax.constants import NUM_ACTIONS
from orgnav_jax.errors import INT32_MAX, is_int, is_number, run_cli


@dataclasses.dataclass(frozen=True)
class Config:
    scene_preset: str = "tiny"
    scenes_dir: str | None = None
    scene_seed: int = 0
    seed: int = 0
    num_envs: int = 32
    num_steps: int = 32            # rollout length per update
    total_timesteps: int = 150_000
    update_epochs: int = 4
    num_minibatches: int = 4       # split over environments (whole sequences)
    lr: float = 1e-3
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    ent_coef: float = 0.01
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    hidden: int = 128

    @property
    def num_updates(self) -> int:
        return max(1, self.total_timesteps // (self.num_envs * self.num_steps))

    def check(self) -> "Config":
        """ValueError naming the first field out of range (before anything is built)."""
        for name in ("num_envs", "num_steps", "total_timesteps", "update_epochs",
                     "num_minibatches", "hidden"):
            value = getattr(self, name)
            if not is_int(value) or not 1 <= value <= INT32_MAX:
                raise ValueError(f"{name}: expected an integer >= 1, got {value!r}")
        for name in ("scene_seed", "seed"):
            value = getattr(self, name)
            if not is_int(value) or not 0 <= value <= INT32_MAX:
                raise ValueError(f"{name}: expected an integer >= 0, got {value!r}")
        if self.num_envs % self.num_minibatches:
            raise ValueError(f"num_envs {self.num_envs} is not a multiple of "
                             f"num_minibatches {self.num_minibatches}")
        for name, lo, hi in (("lr", 0, None), ("gamma", 0, 1), ("gae_lambda", 0, 1),
                             ("clip_eps", 0, None), ("ent_coef", 0, None),
                             ("vf_coef", 0, None), ("max_grad_norm", 0, None)):
            value = getattr(self, name)
            if not is_number(value) or value < lo or (hi is not None and value > hi):
                span = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
                raise ValueError(f"{name}: expected a finite number {span}, got {value!r}")
        return self


# --------------------------------------------------------------------------- network
class ScannedGRU(nn.Module):
    """A GRU over time (axis 0) whose carry restarts where an episode started."""

    @functools.partial(nn.scan, variable_broadcast="params", in_axes=0, out_axes=0,
                       split_rngs={"params": False})
    @nn.compact
    def __call__(self, carry, x):
        ins, resets = x
        carry = jnp.where(resets[:, None], jnp.zeros_like(carry), carry)
        carry, y = nn.GRUCell(features=carry.shape[-1])(carry, ins)
        return carry, y

    @staticmethod
    def initial_carry(batch: int, hidden: int):
        return jnp.zeros((batch, hidden))


class ActorCriticGRU(nn.Module):
    hidden: int = 128

    @nn.compact
    def __call__(self, carry, x):
        """carry (B, H); x = (obs (T, B, D), episode starts (T, B)) -> carry, logits
        (T, B, 6), values (T, B)."""
        obs, resets = x
        h = nn.relu(nn.Dense(self.hidden)(nn.LayerNorm()(obs)))
        carry, h = ScannedGRU()(carry, (h, resets))
        a = nn.relu(nn.Dense(self.hidden)(h))
        logits = nn.Dense(NUM_ACTIONS, kernel_init=nn.initializers.orthogonal(0.01))(a)
        v = nn.relu(nn.Dense(self.hidden)(h))
        value = nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0))(v)[..., 0]
        return carry, logits, value


class Transition(NamedTuple):
    start: jax.Array     # the observation starts an episode (the GRU restarts)
    done: jax.Array
    action: jax.Array
    value: jax.Array
    reward: jax.Array
    log_prob: jax.Array
    obs: jax.Array
    success: jax.Array
    spl: jax.Array


def _spl(info):
    opt = info["optimal_len"].astype(jnp.float32)
    return info["success"] * opt / jnp.maximum(info["path_len"], opt).astype(jnp.float32)


def make_env(config: Config, split: str = "train"):
    """(NavEnv, EnvParams) of a split of the config's scenes (flat observations)."""
    return gymnax_env.make(config.scene_preset, split, "flat", seed=config.scene_seed,
                           scenes_dir=config.scenes_dir)


# --------------------------------------------------------------------------- training
def make_train(config: Config, env=None, env_params=None):
    """-> train(key) -> {"params", "metrics"}: the whole run, jittable."""
    config.check()
    if env is None:
        env, env_params = make_env(config)
    env = LogWrapper(env)
    network = ActorCriticGRU(config.hidden)
    n_envs, n_steps = config.num_envs, config.num_steps

    def lr_schedule(count):
        steps_per_update = config.num_minibatches * config.update_epochs
        frac = 1.0 - (count // steps_per_update) / config.num_updates
        return config.lr * frac if config.anneal_lr else config.lr

    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm),
                     optax.adam(lr_schedule, eps=1e-5))

    def train(key):
        key, k_init, k_reset = jax.random.split(key, 3)
        dim = env.observation_space(env_params).shape[0]
        params = network.init(k_init, ScannedGRU.initial_carry(n_envs, config.hidden),
                              (jnp.zeros((1, n_envs, dim)), jnp.zeros((1, n_envs), bool)))
        opt_state = tx.init(params)
        obs, env_state = jax.vmap(env.reset, (0, None))(jax.random.split(k_reset, n_envs),
                                                        env_params)
        carry = ScannedGRU.initial_carry(n_envs, config.hidden)
        start = jnp.ones(n_envs, bool)

        def update(runner, _):
            params, opt_state, env_state, obs, start, carry, key = runner
            carry0 = carry

            def env_step(runner, _):
                params, env_state, obs, start, carry, key = runner
                key, k_act, k_env = jax.random.split(key, 3)
                carry, logits, value = network.apply(params, carry, (obs[None], start[None]))
                logits, value = logits[0], value[0]
                action = jax.random.categorical(k_act, logits)
                log_prob = jax.nn.log_softmax(logits)[jnp.arange(n_envs), action]
                nobs, env_state, reward, term, trunc, info = jax.vmap(
                    env.step, (0, 0, 0, None))(jax.random.split(k_env, n_envs), env_state,
                                               action, env_params)
                done = term | trunc
                t = Transition(start, done, action, value, reward, log_prob, obs,
                               info["success"] & done, _spl(info) * done)
                return (params, env_state, nobs, done, carry, key), t

            (_, env_state, obs, start, carry, key), traj = jax.lax.scan(
                env_step, (params, env_state, obs, start, carry, key), None, n_steps)
            _, _, last_value = network.apply(params, carry, (obs[None], start[None]))
            last_value = last_value[0]

            def gae_step(c, t):
                adv, next_value = c
                delta = t.reward + config.gamma * next_value * (1 - t.done) - t.value
                adv = delta + config.gamma * config.gae_lambda * (1 - t.done) * adv
                return (adv, t.value), adv

            _, advantages = jax.lax.scan(gae_step, (jnp.zeros_like(last_value), last_value),
                                         traj, reverse=True)
            targets = advantages + traj.value

            def loss_fn(params, carry0, traj, adv, targets):
                _, logits, value = network.apply(params, carry0, (traj.obs, traj.start))
                logp_all = jax.nn.log_softmax(logits)
                logp = jnp.take_along_axis(logp_all, traj.action[..., None], -1)[..., 0]
                v_clip = traj.value + jnp.clip(value - traj.value, -config.clip_eps,
                                               config.clip_eps)
                v_loss = 0.5 * jnp.maximum((value - targets) ** 2,
                                           (v_clip - targets) ** 2).mean()
                ratio = jnp.exp(logp - traj.log_prob)
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg = -jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - config.clip_eps,
                                                        1 + config.clip_eps) * adv).mean()
                entropy = -(jnp.exp(logp_all) * logp_all).sum(-1).mean()
                return pg + config.vf_coef * v_loss - config.ent_coef * entropy, (v_loss, entropy)

            def epoch(c, _):
                params, opt_state, key = c
                key, k_perm = jax.random.split(key)
                perm = jax.random.permutation(k_perm, n_envs)
                split = lambda x, ax: jnp.stack(jnp.split(jnp.take(x, perm, ax),  # noqa: E731
                                                          config.num_minibatches, ax))
                batches = (split(carry0, 0), jax.tree_util.tree_map(lambda x: split(x, 1), traj),
                           split(advantages, 1), split(targets, 1))

                def minibatch(c, batch):
                    params, opt_state = c
                    grads, aux = jax.grad(loss_fn, has_aux=True)(params, *batch)
                    updates, opt_state = tx.update(grads, opt_state, params)
                    return (optax.apply_updates(params, updates), opt_state), aux

                (params, opt_state), aux = jax.lax.scan(minibatch, (params, opt_state), batches)
                return (params, opt_state, key), aux

            (params, opt_state, key), aux = jax.lax.scan(
                epoch, (params, opt_state, key), None, config.update_epochs)
            ends = jnp.maximum(traj.done.sum(), 1)
            metrics = {"episodes": traj.done.sum(),
                       "success": traj.success.sum() / ends, "spl": traj.spl.sum() / ends,
                       "return": (env_state.returned_episode_returns).mean(),
                       "value_loss": aux[0].mean(), "entropy": aux[1].mean()}
            return (params, opt_state, env_state, obs, start, carry, key), metrics

        runner = (params, opt_state, env_state, obs, start, carry, key)
        runner, metrics = jax.lax.scan(update, runner, None, config.num_updates)
        return {"params": runner[0], "metrics": metrics}

    return train


def train(config: Config | None = None, env=None, env_params=None):
    """Train with one jit over the whole run -> (params, metrics per update as numpy)."""
    config = Config() if config is None else config
    out = jax.jit(make_train(config, env, env_params))(jax.random.PRNGKey(config.seed))
    return out["params"], jax.tree_util.tree_map(np.asarray, out["metrics"])


# --------------------------------------------------------------------------- evaluation
def evaluate(params, config: Config, env=None, env_params=None, *, split: str = "val",
             num_envs: int = 256, seed: int = 1, policy: str = "trained",
             greedy: bool = False) -> dict[str, float]:
    """Success and SPL over num_envs episodes (each env's first episode) on a split,
    run together under jit; policy "trained" (params, sampled or greedy actions) or
    "random" (uniform actions, params unused)."""
    if not is_int(num_envs) or num_envs < 1:
        raise ValueError(f"num_envs (episodes): expected an integer >= 1, got {num_envs!r} "
                         "(a success rate over no episode is not a number)")
    if policy not in ("trained", "random"):
        raise ValueError(f"policy must be 'trained' or 'random', got {policy!r}")
    if env is None:
        env, env_params = make_env(config, split)
    network = ActorCriticGRU(config.hidden)
    max_steps = int(env_params.max_steps_in_episode)

    @jax.jit
    def run(key):
        k_reset, key = jax.random.split(key)
        obs, state = jax.vmap(env.reset, (0, None))(jax.random.split(k_reset, num_envs),
                                                    env_params)
        carry = ScannedGRU.initial_carry(num_envs, config.hidden)
        zero = jnp.zeros(num_envs)

        def step(c, _):
            obs, state, carry, key, live, success, spl, start = c
            key, k_act, k_env = jax.random.split(key, 3)
            if policy == "random":
                action = jax.random.randint(k_act, (num_envs,), 0, NUM_ACTIONS)
            else:
                carry, logits, _ = network.apply(params, carry, (obs[None], start[None]))
                action = (jnp.argmax(logits[0], -1) if greedy
                          else jax.random.categorical(k_act, logits[0]))
            obs, state, _, term, trunc, info = jax.vmap(env.step, (0, 0, 0, None))(
                jax.random.split(k_env, num_envs), state, action, env_params)
            done = term | trunc
            end = live & done
            success = success + end * info["success"]
            spl = spl + end * _spl(info)
            return (obs, state, carry, key, live & ~done, success, spl, done), None

        c = (obs, state, carry, key, jnp.ones(num_envs, bool), zero, zero,
             jnp.ones(num_envs, bool))
        c, _ = jax.lax.scan(step, c, None, max_steps)
        return c[5].mean(), c[6].mean(), c[4].sum()

    success, spl, unfinished = run(jax.random.PRNGKey(seed))
    assert int(unfinished) == 0   # every episode ends within the largest cap
    return {"success": float(success), "spl": float(spl), "episodes": num_envs}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default="tiny", help="scene preset (default tiny)")
    p.add_argument("--scenes-dir", default=None, help="a saved SceneSet instead")
    p.add_argument("--total-timesteps", type=int, default=Config.total_timesteps)
    p.add_argument("--num-envs", type=int, default=Config.num_envs)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-episodes", type=int, default=512)
    a = p.parse_args(argv)
    for option, value, lo in (("--num-envs", a.num_envs, 1),
                              ("--total-timesteps", a.total_timesteps, 1),
                              ("--seed", a.seed, 0), ("--eval-episodes", a.eval_episodes, 1)):
        if not lo <= value <= INT32_MAX:
            raise ValueError(f"{option}: expected an integer >= {lo}, got {value}")
    config = Config(scene_preset=a.scenes, scenes_dir=a.scenes_dir, seed=a.seed,
                    total_timesteps=a.total_timesteps, num_envs=a.num_envs).check()
    make_env(config, "val")          # the scenes exist and have val rooms, before training
    t0 = time.perf_counter()
    params, metrics = train(config)
    seconds = time.perf_counter() - t0
    for i in np.linspace(0, config.num_updates - 1, min(10, config.num_updates)).astype(int):
        print(f"update {i + 1:5d}  train success {metrics['success'][i]:.3f}  "
              f"SPL {metrics['spl'][i]:.3f}  entropy {metrics['entropy'][i]:.2f}")
    env, env_params = make_env(config, "val")
    res = {name: evaluate(params, config, env, env_params, num_envs=a.eval_episodes,
                          policy=name) for name in ("trained", "random")}
    steps = config.num_updates * config.num_envs * config.num_steps
    print(f"{steps} env steps in {seconds:.0f} s (compile included)")
    for name, r in res.items():
        print(f"val {name:8s} success {r['success']:.3f}  SPL {r['spl']:.3f}  "
              f"({r['episodes']} episodes)")
    print(json.dumps({"env_steps": steps, "seconds": round(seconds, 1),
                      **{f"val_{k}_{m}": round(v[m], 4) for k, v in res.items()
                         for m in ("success", "spl")}}))


if __name__ == "__main__":
    sys.exit(run_cli(main))     # the CLIs' convention: `error: ...`, exit 2 (orgnav_jax.errors)
