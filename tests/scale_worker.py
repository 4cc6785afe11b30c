"""Scale-out checks run in a subprocess (tests/test_scale_out.py): the forced host
device count must be set before jax is imported, which pytest's process has done.

    python tests/scale_worker.py TASK|all OUT_DIR SCENES_DIR [ARGS...]

Each task writes what the test compares under OUT_DIR (npz of the final runners' leaves,
result.json) and exits 0; the test asserts on them.
"""

from __future__ import annotations

import json
import os
import sys

if "--xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                               + " --xla_force_host_platform_device_count=2").strip()

import jax  # noqa: E402
import numpy as np  # noqa: E402

from helpers import CHUNK, small_cfg  # noqa: E402  (tests/ is this script's directory)


def save_leaves(path, tree):
    np.savez(path, *[np.asarray(x) for x in jax.tree_util.tree_leaves(tree)])


# Every task trains this one computation (IL and dropout on), so the process compiles
# three chunks in all (one device, two devices, a population on two devices), each once
# (the trainer's own cache: loop.cached_train_chunk). A checkpoint every 2 chunks (after
# chunks 2 and 4: the killed runs stop after 2) cuts the worker's orbax saves from 50 to
# 30 (the best-on-val ones stay), 9.7 s to 4.9 s.
KW = dict(il="deadlock", dropout=0.25, checkpoint_every_chunks=2)


def task_chunk(out, scenes_dir):
    """3 chunks on one device and on a 2-device mesh from the same runner."""
    from orgnav_jax import scenes as S
    from orgnav_jax.models import build_model
    from orgnav_jax.training import loop, scale
    from orgnav_jax.training.update import init_runner
    cfg = small_cfg(scenes_dir, out, **KW)
    train = S.load(scenes_dir).split_view("train").to_device()
    model = build_model(cfg, train)
    mesh = scale.make_mesh(2)
    opt, one = loop.cached_train_chunk(loop.compute_config(cfg), model)
    _, two = loop.cached_train_chunk(loop.compute_config(cfg), model, mesh)
    runner = init_runner(cfg, model, opt, train, jax.random.PRNGKey(0))
    r1, r2 = runner, scale.place(runner, scale.runner_shardings(runner, mesh))
    s2 = scale.place(train, scale.replicated(train, mesh))
    losses = []
    for _ in range(3):
        r1, m1 = one(r1, train)
        r2, m2 = two(r2, s2)
        losses.append([float(m1["loss"]), float(m2["loss"])])
    hlo = two.lower(r2, s2).compile().as_text()
    save_leaves(os.path.join(out, "one.npz"), r1)
    save_leaves(os.path.join(out, "two.npz"), r2)
    result = {"losses": losses, "devices": len(jax.devices()),
              "fresh_devices": len(r2.fresh.sharding.device_set),
              "fresh_spec": str(r2.fresh.sharding.spec),
              "params_replicated": all(x.sharding.is_fully_replicated
                                       for x in jax.tree_util.tree_leaves(r2.params)),
              "all_reduce": hlo.count("all-reduce("), "all_gather": hlo.count("all-gather("),
              "compiles": two._cache_size()}
    with open(os.path.join(out, "result.json"), "w") as f:
        json.dump(result, f)


def task_runs(out, scenes_dir):
    """Full and killed-then-resumed runs on 2 devices; a 1-device run resumed on 2."""
    from orgnav_jax.training import loop
    res = {}
    full2 = loop.train(small_cfg(scenes_dir, f"{out}/full2", devices=2, **KW), progress=False)
    save_leaves(f"{out}/full2.npz", full2["runner"])
    cfg = small_cfg(scenes_dir, f"{out}/killed2", devices=2, **KW)
    res["killed2_chunks"] = loop.train(cfg, progress=False, stop_after_chunks=2)["chunks"]
    resumed = loop.train(cfg, resume=True, progress=False)
    res["resumed2_chunks"] = resumed["chunks"]
    save_leaves(f"{out}/resumed2.npz", resumed["runner"])
    full1 = loop.train(small_cfg(scenes_dir, f"{out}/full1", devices=1, **KW), progress=False)
    save_leaves(f"{out}/full1.npz", full1["runner"])
    cfg1 = small_cfg(scenes_dir, f"{out}/one_then_two", devices=1, **KW)
    loop.train(cfg1, progress=False, stop_after_chunks=2)
    moved = loop.train(small_cfg(scenes_dir, f"{out}/one_then_two", devices=2, **KW),
                       resume=True, progress=False)
    res["moved_chunks"] = moved["chunks"]
    res["moved_fresh_devices"] = len(moved["runner"].fresh.sharding.device_set)
    save_leaves(f"{out}/one_then_two.npz", moved["runner"])
    # a finished 2-chunk run (its budget ends on a val chunk; devices 0: all of a process's
    # own) that the two-process test resumes as two processes with a 4-chunk budget
    res["half2_chunks"] = loop.train(small_cfg(scenes_dir, f"{out}/half2",
                                               total_env_steps=2 * CHUNK, **KW),
                                     progress=False)["chunks"]
    with open(f"{out}/result.json", "w") as f:
        json.dump(res, f)


def task_seeds(out, scenes_dir):
    """Seeds 0 and 1 in one program on 2 devices, whole and killed-then-resumed; the
    same seeds as separate 1-device runs."""
    from orgnav_jax.training import loop
    res = {}
    pop = loop.train_seeds(small_cfg(scenes_dir, f"{out}/pop", devices=2, **KW), [0, 1],
                           progress=False)
    cfg = small_cfg(scenes_dir, f"{out}/killed", devices=2, **KW)
    first = loop.train_seeds(cfg, [0, 1], progress=False, stop_after_chunks=2)
    res["killed_chunks"] = [r["chunks"] for r in first]
    resumed = loop.train_seeds(cfg, [0, 1], resume=True, progress=False)
    res["resumed_chunks"] = [r["chunks"] for r in resumed]
    for seed, p, r in zip((0, 1), pop, resumed):
        save_leaves(f"{out}/pop-s{seed}.npz", p["runner"])
        save_leaves(f"{out}/resumed-s{seed}.npz", r["runner"])
        one = loop.train(small_cfg(scenes_dir, f"{out}/one-s{seed}", devices=1, seed=seed,
                                   **KW), progress=False)
        save_leaves(f"{out}/one-s{seed}.npz", one["runner"])
    res["fresh_devices"] = len(pop[0]["runner"].fresh.sharding.device_set)
    with open(f"{out}/result.json", "w") as f:
        json.dump(res, f)


TASKS = {"chunk": task_chunk, "runs": task_runs, "seeds": task_seeds}

if __name__ == "__main__":
    task, out, scenes_dir, *rest = sys.argv[1:]
    # "all": every task in this one process (one start, shared compiles), each in OUT/TASK
    for name in (TASKS if task == "all" else [task]):
        where = os.path.join(out, name) if task == "all" else out
        os.makedirs(where, exist_ok=True)
        TASKS[name](where, scenes_dir, *rest)
