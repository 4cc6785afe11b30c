"""Benchmark: evaluation env-steps/s with TPN's test-time updates vs without.

    python benchmarks/tpn_eval_throughput.py                     # small widths
    python benchmarks/tpn_eval_throughput.py --presets small paper --num-envs 256 1000

For each training preset's widths and each batch size B, it compiles the jitted
evaluation scan (`evaluation._run_batch`: B episodes, `--steps` steps, vmapped env and
policy) for:

* plain:  the navigation model alone (greedy);
* tpn:    + TPN (internal memory read every step) and one SGD step on deadlock steps of
          the actor head (`--scope actor`): the model up to the LSTM runs once, shared;
          the action comes from the updated weights;
* tpn-all:  as tpn, updating on every step (Table 2's "all");
* tpn-params: as tpn, on all parameters of the navigation network (`--scope all`, the
          default): low-rank fast weights (tpn/lowrank.py, reset_every 50: 50 slots);
          the model runs forward, backward and again with the updated weights;
* tpn-params-dense (not run by default): the same with a full copy of all parameters
          per episode (the reference implementation), at the batch
          `tpn.policy.default_batch_size` allows it (it reports the batch it ran).

Under vmap both branches of "update or not" are computed on every step, so the cost does
not depend on how many steps are deadlocks: the numbers are the worst case. Weights are
freshly initialised (throughput does not depend on them: the scan runs all `--steps`).
Scenes: the tiny preset with the preset's feature projections swapped in (as in
train_throughput.py). Compile time is reported apart.

Last line: {"results": [{"preset", "policy", "num_envs", "env_steps_per_s", "compile_s",
"ratio_to_plain"}, ...], "min_ratio": ...}
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from train_throughput import bench_scenes  # noqa: E402

from orgnav_jax import env, evaluation
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.models import build_model, init_params
from orgnav_jax.scenes import load_or_build
from orgnav_jax.tpn.config import get_tpn_config
from orgnav_jax.tpn.test_time import build_tpn, default_batch_size, init_tpn_params, tpn_policy
from orgnav_jax.training.config import get_config
from orgnav_jax.training.runs import model_policy

# name -> (TPNConfig fields, fast-weights impl)
VARIANTS = {"tpn": ({"scope": "actor"}, "auto"),
            "tpn-all": ({"scope": "actor", "when": "all"}, "auto"),
            "tpn-params": ({"scope": "all"}, "lowrank"),
            "tpn-params-dense": ({"scope": "all"}, "dense")}
DEFAULT_VARIANTS = ["tpn", "tpn-all", "tpn-params"]


def time_policy(policy, params, scenes, episodes, steps: int, repeats: int):
    """-> (env-steps/s best of repeats, compile s) of one batch of episodes."""
    args = (policy, params, scenes, jax.numpy.asarray(episodes.scene),
            jax.numpy.asarray(episodes.start), jax.numpy.asarray(episodes.target),
            jax.random.PRNGKey(0), env.EnvParams.evaluation(), steps)
    t0 = time.perf_counter()
    compiled = evaluation._run_batch.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    dynamic = (params, scenes) + args[3:7]
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*dynamic))
        best = min(best, time.perf_counter() - t0)
    return len(episodes.scene) * steps / best, compile_s


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["small"])
    ap.add_argument("--model", default="baseline")
    ap.add_argument("--num-envs", type=int, nargs="+", default=[256, 1000])
    ap.add_argument("--steps", type=int, default=100, help="steps per episode batch")
    ap.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, choices=list(VARIANTS))
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(f"jax {jax.__version__} backend {jax.default_backend()}", flush=True)
    tiny = load_or_build("tiny", 0).split_view("train")
    rows = []
    print(f"{'preset':<6} {'policy':<16} {'B':>5} {'compile s':>9} {'env-steps/s':>12} "
          f"{'vs plain':>8}\n" + "-" * 62, flush=True)
    for preset in args.presets:
        scenes = bench_scenes(tiny, preset)
        cfg = get_config(preset, model=args.model)
        model = build_model(cfg, scenes)
        params = init_params(model, jax.random.PRNGKey(0), scenes)
        for n in args.num_envs:
            episodes = sample_episodes(scenes, -(-n // 4), seed=0)
            episodes = episodes.subset(np.arange(n) % len(episodes))
            plain, c = time_policy(model_policy(model), params, scenes, episodes,
                                   args.steps, args.repeats)
            rows.append(dict(preset=preset, policy="plain", num_envs=n,
                             env_steps_per_s=round(plain, 1), compile_s=round(c, 2),
                             ratio_to_plain=1.0))
            for name in args.variants:
                fields, impl = VARIANTS[name]
                tcfg = get_tpn_config(**fields)
                tpn = build_tpn(cfg, tcfg)
                pp = {"base": params, "tpn": init_tpn_params(tpn, cfg, jax.random.PRNGKey(1))}
                b = n if impl != "dense" else min(n, default_batch_size(params, tcfg, impl))
                sps, c = time_policy(tpn_policy(model, tpn, tcfg, name, 0.0, impl), pp, scenes,
                                     episodes.subset(np.arange(b)), args.steps, args.repeats)
                rows.append(dict(preset=preset, policy=name, num_envs=b,
                                 env_steps_per_s=round(sps, 1), compile_s=round(c, 2),
                                 ratio_to_plain=round(sps / plain, 3)))
            for r in rows[-1 - len(args.variants):]:
                print(f"{r['preset']:<6} {r['policy']:<16} {r['num_envs']:>5} "
                      f"{r['compile_s']:>9.2f} {r['env_steps_per_s']:>12.0f} "
                      f"{r['ratio_to_plain']:>8.3f}", flush=True)
    print(json.dumps({"results": rows,
                      "min_ratio": min(r["ratio_to_plain"] for r in rows)}))


if __name__ == "__main__":
    main()
