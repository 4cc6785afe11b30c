"""Benchmark: environment steps per second, JAX (jit + vmap, auto-reset) vs the reference.

    python benchmarks/env_throughput.py                       # small preset, 1..8192 envs
    python benchmarks/env_throughput.py --num-envs 1024 --preset tiny

The JAX env runs random actions with auto-reset in a `lax.scan` of --steps steps under
one jit; compile time is reported apart. The reference env (plain Python dicts keyed by
state strings, `orgnav_jax.reference_env`) runs random actions one step at a time.
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

from orgnav_jax import env
from orgnav_jax.constants import NUM_ACTIONS
from orgnav_jax.reference_env import ReferenceEnv
from orgnav_jax.scenes import load_or_build


def make_runner(scenes, params, num_envs: int, steps: int):
    """A jitted function key -> (finished episodes, summed reward, a checksum of the
    observations) running num_envs envs for `steps` steps of random actions with
    auto-reset. Every output of the step feeds the result, as a policy would consume
    it: without that XLA drops whatever the returned value does not need (a benchmark
    that returned only the finished count computed steps and scenes, not the moves,
    the trail or the observations, and looked 3x faster than the env is)."""
    v_reset = jax.vmap(env.reset, in_axes=(0, None, None))
    v_step = jax.vmap(env.step, in_axes=(0, 0, 0, None, None))

    @jax.jit
    def run(key, scenes):
        k0, k1 = jax.random.split(key)
        _, state = v_reset(jax.random.split(k0, num_envs), scenes, params)

        def body(carry, key):
            state, finished, reward_sum, check = carry
            k_act, k_env = jax.random.split(key)
            actions = jax.random.randint(k_act, (num_envs,), 0, NUM_ACTIONS)
            obs, state, reward, done, _ = v_step(jax.random.split(k_env, num_envs), state,
                                                 actions, scenes, params)
            check = (check + obs.det_conf.sum() + obs.det_box.sum() + obs.deadlock.sum()
                     + obs.state.sum() + obs.target.sum() + obs.prev_action.sum())
            return (state, finished + done.sum(), reward_sum + reward.sum(), check), None

        init = (state, jnp.int32(0), jnp.float32(0), jnp.float32(0))
        (_, finished, reward_sum, check), _ = jax.lax.scan(body, init,
                                                           jax.random.split(k1, steps))
        return finished, reward_sum, check

    return run


def time_jax(scenes, params, num_envs: int, steps: int, repeats: int) -> dict:
    run = make_runner(scenes, params, num_envs, steps)
    key = jax.random.PRNGKey(0)
    t0 = time.perf_counter()
    compiled = run.lower(key, scenes).compile()
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for r in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(jax.random.PRNGKey(r + 1), scenes))
        best = min(best, time.perf_counter() - t0)
    return {"num_envs": num_envs, "steps": steps, "compile_s": round(compile_s, 3),
            "run_s": round(best, 4), "steps_per_s": num_envs * steps / best}


def time_reference(scenes, seconds: float = 3.0) -> float:
    """Random actions with resets, one Python step at a time -> steps/s."""
    ref = ReferenceEnv.from_sceneset(scenes)
    rng = np.random.default_rng(0)
    names = list(ref.scenes)
    keys = {n: sorted(s.states) for n, s in ref.scenes.items()}
    steps, done, t0 = 0, True, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        if done:
            n = names[rng.integers(len(names))]
            ref.reset(n, keys[n][rng.integers(len(keys[n]))], "Sink")
        _, _, done, _ = ref.step(int(rng.integers(NUM_ACTIONS)))
        steps += 1
    return steps / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--num-envs", type=int, nargs="+", default=[1, 64, 1024, 8192])
    ap.add_argument("--env-steps", type=int, default=2_000_000,
                    help="env steps per timed run (num_envs x scan length)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    scenes = load_or_build(args.preset).split_view("train").to_device()
    params = env.EnvParams()
    rows = []
    for n in args.num_envs:
        steps = max(16, args.env_steps // n)
        if n == 1:
            steps = min(steps, 20_000)
        rows.append(time_jax(scenes, params, n, steps, args.repeats))
        r = rows[-1]
        print(f"num_envs {n:6d}  scan {r['steps']:6d}  compile {r['compile_s']:6.2f} s  "
              f"{r['steps_per_s'] / 1e6:8.3f} M steps/s", flush=True)
    ref = time_reference(scenes)
    best = max(r["steps_per_s"] for r in rows)
    print(f"reference env (Python dicts): {ref / 1e3:.1f} k steps/s; "
          f"best JAX / reference = {best / ref:.0f}x")
    print(json.dumps({"benchmark": "env_throughput", "preset": args.preset,
                      "cpu_count": os.cpu_count(), "platform": platform.platform(),
                      "jax_backend": jax.default_backend(), "rows": rows,
                      "jax_steps_per_s": best, "reference_steps_per_s": ref,
                      "ratio": best / ref}))


if __name__ == "__main__":
    main()
