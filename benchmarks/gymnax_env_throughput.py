"""Benchmark: the gymnax environment (orgnav_jax.gymnax_env.NavEnv) next to orgnav_jax.env.

    python benchmarks/gymnax_env_throughput.py                 # small preset, 64 and 1024 envs
    python benchmarks/gymnax_env_throughput.py --preset tiny --num-envs 256

Random actions with auto-reset, a `lax.scan` of steps under one jit (compile apart, best
of --repeats), each step's observation summed into the carry so that XLA cannot drop it:

- orgnav_jax.env: the index observation (detections, one-hots; no large features);
- NavEnv flat: the decoded observation (global feature map, appearance, ...), i.e. the
  feature decode the models otherwise do inside their own forward pass;
- NavEnv, obs unused: the same step with the observation not read (XLA drops the
  decode): the cost of the gymnax layer itself;
- GymnaxToVectorGymWrapper: a gymnasium vector env, one host round trip per step (numpy
  actions in, the flat observation copied out to numpy), what a PyTorch agent sees.

Prints a table, then one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from gymnax.wrappers import GymnaxToVectorGymWrapper

from orgnav_jax import env, gymnax_env
from orgnav_jax.constants import NUM_ACTIONS
from orgnav_jax.scenes import load_or_build


def scan_runner(step_fn, reset_fn, num_envs: int, steps: int):
    """jit(key) -> checksum: num_envs envs, `steps` random actions each, auto-reset;
    step_fn(keys, state, actions) -> (obs, state, value summed into the checksum)."""
    @jax.jit
    def run(key):
        k0, k1 = jax.random.split(key)
        _, state = reset_fn(jax.random.split(k0, num_envs))

        def body(carry, key):
            state, total = carry
            k_act, k_env = jax.random.split(key)
            actions = jax.random.randint(k_act, (num_envs,), 0, NUM_ACTIONS)
            state, value = step_fn(jax.random.split(k_env, num_envs), state, actions)
            return (state, total + value), None

        (_, total), _ = jax.lax.scan(body, (state, jnp.float32(0)), jax.random.split(k1, steps))
        return total

    return run


def time_scan(run, num_envs: int, steps: int, repeats: int) -> dict:
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    compiled = run.lower(key).compile()
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(jax.random.PRNGKey(r + 1)))
        best = min(best, time.perf_counter() - t0)
    return {"num_envs": num_envs, "steps": steps, "compile_s": round(compile_s, 2),
            "steps_per_s": num_envs * steps / best}


def time_vector_gym(nav_env, params, num_envs: int, steps: int, repeats: int) -> dict:
    venv = GymnaxToVectorGymWrapper(nav_env, num_envs=num_envs, params=params, seed=0)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    venv.reset(seed=0)
    venv.step(rng.integers(0, NUM_ACTIONS, num_envs))        # compiles reset and step
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(steps):
            obs, reward, term, trunc, _ = venv.step(rng.integers(0, NUM_ACTIONS, num_envs))
            obs, reward = np.asarray(obs), np.asarray(reward)   # to the host, as for torch
        best = min(best, time.perf_counter() - t0)
    return {"num_envs": num_envs, "steps": steps, "compile_s": round(compile_s, 2),
            "steps_per_s": num_envs * steps / best}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--num-envs", type=int, nargs="+", default=[64, 1024])
    ap.add_argument("--env-steps", type=int, default=500_000,
                    help="env steps per timed jitted run (num_envs x scan length)")
    ap.add_argument("--gym-steps", type=int, default=200,
                    help="host steps per timed run of the gymnasium vector env")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    scenes = load_or_build(args.preset).split_view("train").to_device()
    rules = env.EnvParams()
    params = gymnax_env.make_params(scenes, rules)          # the same device arrays
    nav_env = gymnax_env.NavEnv("flat", max(rules.step_caps), params)
    dim = nav_env.observation_space(params).shape[0]
    print(f"{args.preset} train rooms: {scenes.num_scenes} rooms, flat observation {dim} "
          f"floats ({4 * dim} bytes)")

    v_env_reset = jax.vmap(lambda k: env.reset(k, scenes, rules))
    v_env_step = jax.vmap(lambda k, s, a: env.step(k, s, a, scenes, rules))
    v_reset = jax.vmap(nav_env.reset, (0, None))
    v_step = jax.vmap(nav_env.step, (0, 0, 0, None))

    def env_step(keys, state, actions):
        obs, state, _, _, _ = v_env_step(keys, state, actions)
        return state, obs.det_conf.sum() + obs.target.sum() + obs.prev_action.sum()

    def nav_flat(keys, state, actions):
        obs, state, *_ = v_step(keys, state, actions, params)
        return state, obs.sum()

    def nav_unused(keys, state, actions):
        obs, state, reward, *_ = v_step(keys, state, actions, params)
        return state, reward.sum()

    kinds = {"orgnav_jax.env (index obs)": (env_step, v_env_reset),
             "NavEnv flat (decoded obs)": (nav_flat, lambda k: v_reset(k, params)),
             "NavEnv, obs unused": (nav_unused, lambda k: v_reset(k, params))}
    rows = []
    for n in args.num_envs:
        steps = max(16, args.env_steps // n)
        for name, (step_fn, reset_fn) in kinds.items():
            r = {"kind": name, **time_scan(scan_runner(step_fn, reset_fn, n, steps), n, steps,
                                          args.repeats)}
            rows.append(r)
            print(f"{name:30s} num_envs {n:5d}  compile {r['compile_s']:5.2f} s  "
                  f"{r['steps_per_s'] / 1e6:7.3f} M steps/s", flush=True)
    for n in (16,) + tuple(args.num_envs):
        r = {"kind": "GymnaxToVectorGymWrapper",
             **time_vector_gym(nav_env, params, n, args.gym_steps, args.repeats)}
        rows.append(r)
        print(f"{r['kind']:30s} num_envs {n:5d}  compile {r['compile_s']:5.2f} s  "
              f"{r['steps_per_s'] / 1e6:7.3f} M steps/s", flush=True)
    print(json.dumps({"benchmark": "gymnax_env_throughput", "preset": args.preset,
                      "obs_floats": dim, "cpu_count": os.cpu_count(),
                      "platform": platform.platform(), "jax_backend": jax.default_backend(),
                      "rows": rows}))


if __name__ == "__main__":
    main()
