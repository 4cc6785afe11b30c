"""The host loop both training stages share: jitted chunks, logs, val, best, checkpoints.

    stage = Stage(name="train baseline", chunk=..., validate=..., ...)
    summary = run_stage(stage, runner, cfg, run_dir, resume, progress)

A stage (navigation training in training/loop.py, the TPN's stage 2 in tpn/stage2.py)
supplies its jitted chunk, its val evaluation and what "better" means; `run_stage` does
the rest: resume from the newest readable checkpoint, config.json, metrics.jsonl and
TensorBoard (records after the resumed checkpoint dropped), the progress bar, the
non-finite-loss stop, val every `eval_every_chunks` chunks with the best-on-val
checkpoint, the latest-N checkpoints every `checkpoint_every_chunks` chunks, and the
compile time of the first chunk. The caller holds the run directory open (checked and
locked: training/run_dir.py).
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm import tqdm

from orgnav_jax.errors import UserError
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.run_dir import MetricsLog, write_config


class NonFiniteLoss(UserError, RuntimeError):
    """The loss became NaN or infinite; the last good checkpoint is kept."""


@dataclasses.dataclass(frozen=True)
class Stage:
    """What a training stage gives the host loop.

    chunk(runner) -> (runner, metrics): one jitted chunk; metrics device scalars with a
        bool 'loss_finite'.
    summarize(metrics) -> the train record (floats) of one chunk's host metrics.
    validate(runner) -> the val record (floats).
    score_keys: val fields compared in order (higher is better) to keep the best.
    best_keys: val fields kept in the 'best' record (with the step).
    progress_keys: train-record fields shown on the progress bar (mean of the last 10).
    """
    name: str                      # progress-bar label, e.g. "train baseline"
    unit: str                      # "step" or "ep"
    step_name: str                 # the log's step field: "env_steps" or "episodes"
    rate_key: str                  # the train record's speed: "steps_per_s", "episodes_per_s"
    per_chunk: int                 # env steps (episodes) per chunk
    total: int                     # the budget in env steps (episodes): whole chunks
    chunk: Callable[[Any], tuple[Any, dict]]
    summarize: Callable[[dict], dict]
    validate: Callable[[Any], dict]
    score_keys: tuple[str, ...]
    best_keys: tuple[str, ...]
    progress_keys: tuple[str, ...] = ()

    @property
    def num_chunks(self) -> int:
        return max(1, math.ceil(self.total / self.per_chunk))

    def score(self, record: dict) -> tuple:
        return tuple(record.get(k, -math.inf) for k in self.score_keys)


def run_stage(stage: Stage, runner, cfg, run_dir: Path, resume: bool, progress: bool = True,
              stop_after_chunks: int | None = None) -> dict:
    """Run (or resume) `stage` from `runner` in the open run directory -> summary dict:
    run_dir, chunks, the step count under stage.step_name, best_val, compile and wall
    time, and the final runner. stop_after_chunks ends early (tests of kill-and-resume)."""
    ckpt = RunCheckpoints(run_dir, cfg.keep_checkpoints)
    best = {k: -1.0 for k in stage.score_keys}
    chunk = 0
    if resume and ckpt.latest_step() is not None:
        runner, meta = ckpt.restore(runner, fallback=True)
        chunk, best = meta["chunk"], meta["best"]
    write_config(run_dir, cfg)      # after the restore: a failed resume changes nothing
    log = MetricsLog(run_dir, step_name=stage.step_name,
                     resume_from=chunk * stage.per_chunk if resume else None)
    if resume:
        ckpt.drop_best_after(chunk * stage.per_chunk)
    num_chunks = stage.num_chunks
    bar = tqdm(total=num_chunks * stage.per_chunk, initial=chunk * stage.per_chunk,
               unit=stage.unit, unit_scale=True, desc=stage.name, disable=not progress,
               file=sys.stderr)
    recent: dict[str, list] = {k: [] for k in stage.progress_keys}
    t_start, compile_s = time.perf_counter(), None
    try:
        while chunk < num_chunks:
            t0 = time.perf_counter()
            new_runner, metrics = stage.chunk(runner)
            metrics = {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}
            finite = bool(metrics.pop("loss_finite"))
            dt = time.perf_counter() - t0
            compile_s = dt if compile_s is None else compile_s
            if not finite:
                raise NonFiniteLoss(f"non-finite loss in chunk {chunk + 1} of {stage.name}; "
                                    "the run stopped and the last good checkpoint in "
                                    f"{run_dir}/checkpoints is kept")
            runner, chunk = new_runner, chunk + 1
            step = chunk * stage.per_chunk
            record = stage.summarize(metrics)
            record[stage.rate_key] = stage.per_chunk / dt
            log.write("train", step, record)
            for k in stage.progress_keys:
                recent[k] = (recent[k] + [record[k]])[-10:]
            bar.update(stage.per_chunk)
            bar.set_postfix(rate=f"{stage.per_chunk / dt:.0f}/s",
                            **{k: f"{np.mean(v):.3f}" for k, v in recent.items()},
                            best_val=f"{best[stage.score_keys[0]]:.3f}")
            last = chunk == num_chunks
            if chunk % cfg.eval_every_chunks == 0 or last:
                val = stage.validate(runner)
                log.write("val", step, val)
                if stage.score(val) > stage.score(best):
                    best = {**{k: val[k] for k in stage.best_keys}, stage.step_name: step}
                    ckpt.save(step, runner, {"chunk": chunk, "val": val}, best=True)
            if chunk % cfg.checkpoint_every_chunks == 0 or last:
                ckpt.save(step, runner, {"chunk": chunk, "best": best})
            if stop_after_chunks is not None and chunk >= stop_after_chunks and not last:
                break
    finally:
        bar.close()
        log.close()
    return {"run_dir": str(run_dir), stage.step_name: chunk * stage.per_chunk,
            "chunks": chunk, "best_val": best, "compile_plus_first_chunk_s": compile_s,
            "wall_s": time.perf_counter() - t_start, "runner": runner}
