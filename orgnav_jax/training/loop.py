"""The outer training loop: jitted chunks, progress, logs, val evaluation, checkpoints.

    result = train(cfg, resume=False)

Each chunk is `cfg.updates_per_chunk` jitted updates. After each chunk the loop logs
(progress bar, metrics.jsonl, TensorBoard), every `eval_every_chunks` evaluates on the
val episodes and keeps the best parameters, every `checkpoint_every_chunks` saves the
whole RunnerState. With resume=True it continues from the latest checkpoint and ends
with the same parameters an uninterrupted run reaches (on the same machine).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from orgnav_jax import env, evaluation
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.errors import UserError
from orgnav_jax.models import build_model
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.config import TrainConfig, load_config
from orgnav_jax.training.policy import model_policy, preflight, split_on_device
from orgnav_jax.training.run_dir import MetricsLog, open_run_dir, write_config
from orgnav_jax.training.update import init_runner, make_optimizer, make_train_chunk


def compute_config(cfg: TrainConfig) -> TrainConfig:
    """cfg without the fields that do not change the jitted computation."""
    return dataclasses.replace(cfg, run_dir="", total_env_steps=1, eval_every_chunks=1,
                               eval_episodes_per_room_type=1, checkpoint_every_chunks=1,
                               keep_checkpoints=1, seed=0)


@functools.lru_cache(maxsize=8)
def cached_train_chunk(cfg: TrainConfig, model):
    """(optimizer, jitted train chunk), shared by runs in one process that differ only in
    seed, budget or run directory (so they compile once)."""
    optimizer = make_optimizer(cfg)
    return optimizer, make_train_chunk(cfg, model, optimizer)


class NonFiniteLoss(UserError, RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


def chunk_summary(m: dict) -> dict:
    """Per-chunk sums -> means (success, SPL, return, length per finished episode)."""
    out = {k: float(v) for k, v in m.items()}
    n = max(out.pop("episodes"), 1.0)
    for k in ("success", "spl", "ret", "length"):
        out[k] = out[k] / n
    out["episodes"] = n
    return out


def validate(model, params, val_scenes, val_episodes) -> dict:
    """Greedy evaluation on the val episodes -> overall metrics."""
    return evaluation.evaluate(model_policy(model), params, val_scenes, val_episodes,
                               env.EnvParams.evaluation())["overall"]


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          stop_after_chunks: int | None = None) -> dict:
    """Train (or resume) the run in cfg.run_dir -> summary dict (best val, env steps).
    stop_after_chunks ends early (for tests of kill-and-resume)."""
    scenes = preflight(cfg)     # config ranges, scenes, memory: before anything is written
    with open_run_dir(cfg.run_dir, cfg, resume, load_config) as run_dir:
        return _train(cfg, scenes, run_dir, resume, progress, stop_after_chunks)


def _train(cfg: TrainConfig, scenes, run_dir: Path, resume: bool, progress: bool,
           stop_after_chunks: int | None) -> dict:
    # one device copy per split in the process (shared with a later evaluation); the
    # test rooms of the memory-mapped set are never read
    train_scenes = split_on_device(cfg, "train")
    val_scenes = split_on_device(cfg, "val")
    val_episodes = sample_episodes(val_scenes, cfg.eval_episodes_per_room_type, seed=0,
                                   split="val")
    model = build_model(cfg, train_scenes)
    optimizer, train_chunk = cached_train_chunk(compute_config(cfg), model)
    runner = init_runner(cfg, model, optimizer, train_scenes, jax.random.PRNGKey(cfg.seed))
    ckpt = RunCheckpoints(run_dir, cfg.keep_checkpoints)
    best = {"success": -1.0, "spl": -1.0}
    chunk = 0
    if resume and ckpt.latest_step() is not None:
        runner, meta = ckpt.restore(runner, fallback=True)
        chunk, best = meta["chunk"], meta["best"]
    num_chunks = math.ceil(cfg.num_updates / cfg.updates_per_chunk)
    steps_per_chunk = cfg.updates_per_chunk * cfg.steps_per_update
    write_config(run_dir, cfg)
    log = MetricsLog(run_dir, resume_from=chunk * steps_per_chunk if resume else None)
    if resume:
        ckpt.drop_best_after(chunk * steps_per_chunk)

    bar = tqdm(total=num_chunks * steps_per_chunk, initial=chunk * steps_per_chunk,
               unit="step", unit_scale=True, desc=f"train {cfg.model}", disable=not progress,
               file=sys.stderr)
    recent = []
    t_start, compile_s = time.perf_counter(), None
    while chunk < num_chunks:
        t0 = time.perf_counter()
        new_runner, metrics = train_chunk(runner, train_scenes)
        metrics = chunk_summary(jax.device_get(metrics))
        dt = time.perf_counter() - t0
        if compile_s is None:
            compile_s = dt
        if not metrics.pop("loss_finite"):
            bar.close()
            log.close()
            raise NonFiniteLoss(f"non-finite loss in chunk {chunk + 1} (updates "
                                f"{chunk * cfg.updates_per_chunk}..); the run stopped and "
                                f"the last good checkpoint in {run_dir}/checkpoints is kept")
        runner, chunk = new_runner, chunk + 1
        env_steps = chunk * steps_per_chunk
        recent = (recent + [metrics["success"]])[-10:]
        metrics["steps_per_s"] = steps_per_chunk / dt
        log.write("train", env_steps, metrics)
        bar.update(steps_per_chunk)
        bar.set_postfix(sps=f"{metrics['steps_per_s']:.0f}",
                        success=f"{np.mean(recent):.3f}", best_val=f"{best['success']:.3f}")
        last = chunk == num_chunks
        if chunk % cfg.eval_every_chunks == 0 or last:
            val = validate(model, runner.params, val_scenes, val_episodes)
            log.write("val", env_steps, val)
            if (val["success"], val["spl"]) > (best["success"], best["spl"]):
                best = {"spl": val["spl"], "success": val["success"], "env_steps": env_steps}
                ckpt.save(env_steps, runner, {"chunk": chunk, "val": val}, best=True)
        if chunk % cfg.checkpoint_every_chunks == 0 or last:
            ckpt.save(env_steps, runner, {"chunk": chunk, "best": best})
        if stop_after_chunks is not None and chunk >= stop_after_chunks and not last:
            break
    bar.close()
    log.close()
    return {"run_dir": str(run_dir), "env_steps": chunk * steps_per_chunk,
            "chunks": chunk, "best_val": best, "compile_plus_first_chunk_s": compile_s,
            "wall_s": time.perf_counter() - t_start, "runner": runner}
