"""Benchmark: build time of the scene presets and of the expert tables alone.

    python benchmarks/scene_build.py                 # both presets, 120 rooms each
    python benchmarks/scene_build.py --rooms 2 1 1   # quick check

Prints a table, then one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time

import jax
import jax.numpy as jnp

from orgnav_jax import scenes
from orgnav_jax.scenes.sceneset.expert import expert_tables
from orgnav_jax.scenes.sceneset.flat import padded_valid, to_padded


def time_expert(s: scenes.SceneSet, repeats: int = 3) -> tuple[float, float]:
    """(compile_s, run_s) of expert_tables on all rooms of `s` in one batched call (the
    rooms padded to the largest for it, as flat.flat_expert_tables does chunk by chunk)."""
    args = [jnp.asarray(to_padded(s, "next_state")), jnp.asarray(to_padded(s, "visible")),
            jnp.asarray(padded_valid(s))]
    t0 = time.perf_counter()
    compiled = expert_tables.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    return compile_s, min(runs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--presets", nargs="+", default=["small", "paper"])
    ap.add_argument("--rooms", nargs=3, type=int, default=None, metavar=("TRAIN", "VAL", "TEST"),
                    help="rooms per type per split (default: the preset's, 20 5 5)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    overrides = {"rooms_per_type": tuple(args.rooms)} if args.rooms else {}
    if not 0 <= args.seed <= 2 ** 31 - 1:
        ap.error(f"--seed {args.seed}: expected an integer 0 <= seed <= 2,147,483,647")
    for name in args.presets:     # every preset before any is built (a traceback after)
        try:
            preset = scenes.get_preset(name, **overrides)
        except ValueError as err:
            ap.error(str(err))
        if preset.raw:
            ap.error(f"preset {name!r} stores raw features and is written to disk room by "
                     "room, not built in memory: time `python -m orgnav_jax.scenes build "
                     f"--preset {name} --out DIR` (it prints its build time)")

    rows = []
    for name in args.presets:
        t0 = time.perf_counter()
        s = scenes.build(name, args.seed, **overrides)
        build_s = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            scenes.save(s, os.path.join(tmp, "s"))
            save_s = time.perf_counter() - t0
            disk_mb = scenes.disk_size(os.path.join(tmp, "s")) / 2**20
        compile_s, expert_s = time_expert(s)
        rows.append({"preset": name, "rooms": s.num_scenes, "states": s.num_states,
                     "max_states": s.max_states, "build_s": round(build_s, 2),
                     "save_s": round(save_s, 2), "disk_mb": round(disk_mb, 1),
                     "global": f"7x7x{s.global_dim}", "appearance_dim": s.appearance_dim,
                     "expert_compile_s": round(compile_s, 2), "expert_s": round(expert_s, 3)})
        del s

    head = ("preset", "rooms", "states", "build_s", "save_s", "disk_mb", "global",
            "expert_compile_s", "expert_s")
    print(" | ".join(f"{h:>16}" for h in head))
    for r in rows:
        print(" | ".join(f"{str(r[h]):>16}" for h in head))
    print(json.dumps({"benchmark": "scene_build", "cpu_count": os.cpu_count(),
                      "machine": platform.machine(), "jax": jax.__version__, "results": rows}))


if __name__ == "__main__":
    main()
