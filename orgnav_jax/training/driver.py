"""The host loop both training stages share: jitted chunks, logs, val, best, checkpoints.

    stage = Stage(name="train baseline+il", chunk=..., validate=..., ...)
    summary = run_stage(stage, runner, cfg, run_dir, resume, progress)
    summaries = run_population(stage, runners, cfgs, run_dirs, resume)   # seeds in one program

A stage (navigation training in training/loop.py, the TPN's stage 2 in tpn/stage2.py)
supplies its jitted chunk, its val evaluation and what "better" means; `run_stage` does
the rest: resume from the newest readable checkpoint, config.json, metrics.jsonl and
TensorBoard (records after the resumed checkpoint dropped), the progress bar, the
non-finite-loss stop, val every `eval_every_chunks` chunks with the best-on-val
checkpoint, the latest-N checkpoints every `checkpoint_every_chunks` chunks, and the
compile time of the first chunk, and (after the third chunk) the wall-time estimate of
the rest of the run from the measured rate, compile excluded. The caller holds the run
directory open (checked and locked: training/run_dir.py).

A population (`run_population`: several seeds of one config) runs one jitted chunk for
all members, whose runners are stacked on a leading axis (the stage's chunk is vmapped
over it); then each member gets its slice of the metrics in its own metrics.jsonl, its
own val evaluation, best-on-val and latest-N checkpoints in its own run directory. A
population resumes from the newest checkpoint step all its members have.

Several processes (jax.distributed): every process runs this loop with the same calls
(the chunk, evaluations and orbax saves are collective or deterministic); process 0
alone writes config.json, the logs and the progress bar.
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
from orgnav_jax.training.run_dir import METRICS_FILE, MetricsLog, read_metrics, write_config
from orgnav_jax.training.scale import is_primary


# A stop criterion: each run's val records so far (in step order) -> a one-line reason to
# end the stage now, or None (tables/convergence.py: stop_when_converged)
StopRule = Callable[[list[list[dict]]], "str | None"]


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
    place(runner) -> the runner the chunk takes: the local runner (stacked for a
        population) put on the device mesh (training/scale.py); default: as it is.
    steps_key: when the env steps of a chunk vary (SAVN: the steps its episodes really
        took, issue 40), the chunk's metric that holds them. The budget `total` then
        counts them: the run stops after the first chunk whose running count reaches it,
        per_chunk is the most a chunk can take, the log's step, the progress bar and the
        checkpoints' steps are the running count. One run only (no population).
    """
    name: str                      # progress-bar label, e.g. "train baseline+il"
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
    place: Callable[[Any], Any] = lambda runner: runner
    steps_key: str | None = None

    @property
    def num_chunks(self) -> int:
        """The run's chunks (the fewest, with steps_key)."""
        return max(1, math.ceil(self.total / self.per_chunk))

    def score(self, record: dict) -> tuple:
        return tuple(record.get(k, -math.inf) for k in self.score_keys)


def run_stage(stage: Stage, runner, cfg, run_dir: Path, resume: bool, progress: bool = True,
              stop_after_chunks: int | None = None, stop: StopRule | None = None) -> dict:
    """Run (or resume) `stage` from `runner` in the open run directory -> summary dict:
    run_dir, chunks (in all), chunks_run (by this call), the step count under
    stage.step_name, best_val, compile and wall time, `stopped` (the stop rule's reason,
    or None) and the final runner.
    stop_after_chunks ends early (tests of kill-and-resume); `stop` see run_population."""
    return run_population(stage, [runner], [cfg], [Path(run_dir)], resume, progress,
                          stop_after_chunks, stacked=False, stop=stop)[0]


@dataclasses.dataclass
class _Member:
    """One run of a population: its config, directory, checkpoints, best and log."""
    cfg: Any
    run_dir: Path
    ckpt: RunCheckpoints
    best: dict
    log: MetricsLog | None = None


def resumed_chunk(meta: dict, step: int, stage: Stage, where: str) -> int:
    """The chunks done by the checkpoint at `step` (its metadata, read by
    checkpoints.read_meta), checked against the run: 1 <= chunk <= the stage's number of
    chunks, chunk x env steps (episodes) per chunk == step, and its best record holding
    the stage's score keys (with stage.steps_key: chunk <= step <= chunk x per_chunk, and
    the chunk before it short of the budget). UserError naming the checkpoint and the
    field otherwise (a resume must not continue from a chunk the run never reached)."""
    chunk = meta["chunk"]
    if stage.steps_key is not None:
        bad = not 1 <= chunk <= step <= chunk * stage.per_chunk or (
            step - stage.per_chunk >= stage.total)
    else:
        bad = not 1 <= chunk <= stage.num_chunks or chunk * stage.per_chunk != step
    if bad and stage.steps_key is not None:
        raise UserError(f"{where} metadata: field 'chunk': {chunk!r} does not fit its step "
                        f"{step:,} (each chunk takes 1 to {stage.per_chunk:,} "
                        f"{stage.unit}s; the budget is {stage.total:,})")
    if bad:
        raise UserError(f"{where} metadata: field 'chunk': expected {step // stage.per_chunk}"
                        f" (its step {step:,} / {stage.per_chunk:,} {stage.unit}s per chunk; "
                        f"the run has {stage.num_chunks} chunks), got {chunk!r}")
    missing = [k for k in stage.score_keys if k not in meta["best"]]
    if missing:
        raise UserError(f"{where} metadata: field 'best' lacks {missing}, expected the "
                        f"best val record ({', '.join(stage.score_keys)})")
    return chunk


def _restore(members: list[_Member], runners: list, stacked: bool,
             stage: Stage) -> tuple[int, int, list]:
    """Resume: each member's runner from its checkpoint -> (chunks done, steps done,
    runners). One
    run takes its newest readable checkpoint; a population the newest step every member
    has (they save together, so at most the last save of a kill differs)."""
    def where(m: _Member, step: int) -> str:
        return f"checkpoint {m.run_dir / 'checkpoints' / str(step)}"

    if not stacked:
        m = members[0]
        if m.ckpt.latest_step() is None:
            return 0, 0, runners
        runner, meta = m.ckpt.restore(runners[0], fallback=True)
        step = m.ckpt.latest_step()          # the one restored (broken ones set aside)
        chunk = resumed_chunk(meta, step, stage, where(m, step))
        m.best = meta["best"]
        return chunk, step, [runner]
    steps = [set(m.ckpt.latest.all_steps()) for m in members]
    if not any(steps):
        return 0, 0, runners
    common = set.intersection(*steps)
    if not common:
        have = "; ".join(f"{m.run_dir}: {sorted(s) or 'none'}" for m, s in zip(members, steps))
        raise UserError(f"--resume: the seeds' runs have no checkpoint step in common ({have}); "
                        "resume them one seed at a time")
    step, chunks, out = max(common), set(), []
    for m, runner in zip(members, runners):
        runner, meta = m.ckpt.restore(runner, step=step)
        chunks.add(resumed_chunk(meta, step, stage, where(m, step)))
        m.best = meta["best"]
        out.append(runner)
    if len(chunks) != 1:
        raise UserError(f"--resume: the seeds' checkpoints at step {step} are at different "
                        f"chunks {sorted(chunks)}; resume them one seed at a time")
    return chunks.pop(), step, out


def _stack(runners: list):
    return jax.tree_util.tree_map(lambda *xs: jax.numpy.stack(xs), *runners)


@jax.jit
def _take(tree, i):
    return jax.tree_util.tree_map(lambda x: x[i], tree)


def _duration(seconds: float) -> str:
    """12 s, 41 min, 3.2 h, 2.5 days."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


ESTIMATE_AFTER = 3     # chunks of this process before the wall-time estimate (1: compile)


def _together(members: int) -> str:
    return f" ({members} runs together)" if members > 1 else ""


def _capped(capped: bool) -> str:
    return "; the budget is a cap, the convergence rule may stop it sooner" if capped else ""


def wall_time_estimate(stage: Stage, chunk: int, seconds: list[float], members: int,
                       timed_steps: float | None = None, steps: int | None = None,
                       capped: bool = False) -> str:
    """The one-line estimate from the chunks timed after the compile chunk (with
    stage.steps_key: timed_steps, the steps they took, and steps, the run's so far);
    capped: a stop rule may end the stage before its budget, which is then a cap."""
    who, cap = _together(members), _capped(capped)
    per_chunk = float(np.mean(seconds))
    where = f"over chunks {chunk - len(seconds) + 1}-{chunk} (compile excluded)"
    if stage.steps_key is not None:
        rate = timed_steps / float(np.sum(seconds))
        return (f"{stage.name}: {rate:,.0f} {stage.unit}s/s {where}: the remaining "
                f"{max(stage.total - steps, 0):,} of {stage.total:,} {stage.unit}s take "
                f"about {_duration(max(stage.total - steps, 0) / rate)} (a whole run: "
                f"{_duration(stage.total / rate)}; evaluations and checkpoints extra{cap})")
    rate = stage.per_chunk * members / per_chunk
    left = (stage.num_chunks - chunk) * per_chunk
    whole = stage.num_chunks * per_chunk
    return (f"{stage.name}: {rate:,.0f} {stage.unit}s/s{who} {where}: the remaining "
            f"{stage.num_chunks - chunk} of {stage.num_chunks} chunks take about "
            f"{_duration(left)} (a whole run: {_duration(whole)}; evaluations and "
            f"checkpoints extra{cap})")


def cycle_estimate(stage: Stage, marks: list[tuple[int, float]], members: int,
                   capped: bool = False) -> str:
    """The one-line estimate with evaluations and checkpoints, from two (chunk, time)
    marks taken after consecutive val evaluations (the first one's compile excluded)."""
    (c0, t0), (c1, t1) = marks
    per_chunk = (t1 - t0) / (c1 - c0)
    return (f"{stage.name}: {stage.per_chunk * members / per_chunk:,.0f} {stage.unit}s/s"
            f"{_together(members)} with evaluations and checkpoints, over chunks "
            f"{c0 + 1}-{c1}: the remaining {stage.num_chunks - c1} of {stage.num_chunks} "
            f"chunks take about {_duration((stage.num_chunks - c1) * per_chunk)}"
            f"{_capped(capped)}")


def run_population(stage: Stage, runners: list, cfgs: list, run_dirs: list[Path],
                   resume: bool, progress: bool = True, stop_after_chunks: int | None = None,
                   stacked: bool = True, stop: StopRule | None = None) -> list[dict]:
    """Run (or resume) several runs of `stage` in one program -> one summary per run (see
    run_stage). With stacked=True the runners are stacked on a leading axis and
    stage.chunk/stage.place take the stack (metrics then have that axis); stage.validate
    takes one member's runner. `stop`, after each val evaluation, gets every run's val
    records so far (a resume's earlier ones included): a reason ends the stage there,
    with a checkpoint, so that a later --resume with a larger budget continues it (a
    resume with the same `stop` that stops at once trains nothing). The
    callers hold the run directories open."""
    primary = is_primary()
    if stage.steps_key is not None and (stacked or len(runners) != 1):
        raise ValueError(f"{stage.name}: a stage counting varying steps runs one run")
    members = [_Member(cfg, Path(d), RunCheckpoints(d, cfg.keep_checkpoints),
                       {k: -1.0 for k in stage.score_keys}) for cfg, d in zip(cfgs, run_dirs)]
    logged = [[] for _ in members]
    if resume:        # a malformed log is refused before anything is written
        for m, records in zip(members, logged):
            if (m.run_dir / METRICS_FILE).exists():
                records += read_metrics(m.run_dir, stage.step_name, skip_broken=True)
    chunk, steps, runners = (_restore(members, runners, stacked, stage) if resume
                             else (0, 0, runners))
    first_chunk = chunk
    if resume and not steps and primary:        # no checkpoint: say so, its log is dropped
        for m, records in zip(members, logged):
            if records:
                print(f"{stage.name}: resume: no checkpoint in {m.run_dir / 'checkpoints'}; "
                      f"training starts again from step 0 (its metrics.jsonl's "
                      f"{len(records)} records, to {stage.step_name} "
                      f"{max(r[stage.step_name] for r in records):,}, are dropped)",
                      file=sys.stderr, flush=True)
    # each run's val records up to the resumed step (the stop rule's history)
    history = [[r for r in records if r["kind"] == "val" and r[stage.step_name] <= steps]
               for records in logged]
    # a resume the rule already stops (it stopped there before) trains no further
    stopped = stop(history) if stop is not None and resume and all(history) else None
    for m in members:      # after the restore: a failed resume changes nothing
        if primary:
            write_config(m.run_dir, m.cfg)
            m.log = MetricsLog(m.run_dir, step_name=stage.step_name,
                               resume_from=steps if resume else None)
        if resume:
            m.ckpt.drop_best_after(steps)
    runner = stage.place(_stack(runners) if stacked else runners[0])
    member_runner = (lambda i: _take(runner, i)) if stacked else (lambda i: runner)
    num_chunks = stage.num_chunks
    varying = stage.steps_key is not None

    def done(chunk: int, steps: int) -> bool:
        return steps >= stage.total if varying else chunk >= num_chunks

    bar = tqdm(total=stage.total if varying else num_chunks * stage.per_chunk, initial=steps,
               unit=stage.unit, unit_scale=True, desc=stage.name,
               disable=not (progress and primary), file=sys.stderr)
    recent: dict[str, list] = {k: [] for k in stage.progress_keys}
    t_start, compile_s, timed, timed_steps = time.perf_counter(), None, [], 0.0
    marks = []                     # (chunk, time) after each val evaluation and its saves
    if stopped and primary:
        print(f"{stage.name}: resumed at {steps:,} {stage.unit}s, stopped there: {stopped}",
              file=sys.stderr, flush=True)
    try:
        while not done(chunk, steps) and not stopped:
            t0 = time.perf_counter()
            new_runner, metrics = stage.chunk(runner)
            metrics = {k: np.asarray(v) for k, v in jax.device_get(metrics).items()}
            finite = np.atleast_1d(metrics.pop("loss_finite"))
            dt = time.perf_counter() - t0
            took = (int(np.asarray(metrics[stage.steps_key]).sum()) if varying
                    else stage.per_chunk)
            if compile_s is None:
                compile_s = dt
            else:
                timed.append(dt)
                timed_steps += took
            if not finite.all():
                bad = [str(m.run_dir) for m, ok in zip(members, finite) if not ok]
                where = f" (run {', '.join(bad)})" if stacked else ""
                raise NonFiniteLoss(f"non-finite loss in chunk {chunk + 1} of {stage.name}"
                                    f"{where}; the run stopped and the last good checkpoint "
                                    f"in {bad[0]}/checkpoints is kept")
            runner, chunk, steps = new_runner, chunk + 1, steps + took
            step = steps
            for i, m in enumerate(members):
                record = stage.summarize({k: v[i] for k, v in metrics.items()} if stacked
                                         else metrics)
                record[stage.rate_key] = took / dt
                if m.log:
                    m.log.write("train", step, record)
                for k in stage.progress_keys:
                    recent[k] = (recent[k] + [record[k]])[-10 * len(members):]
            bar.update(took)
            last = done(chunk, steps)
            if len(timed) == ESTIMATE_AFTER - 1 and not last and primary:
                bar.write(wall_time_estimate(stage, chunk, timed, len(members), timed_steps,
                                             steps, capped=stop is not None), file=sys.stderr)
            evaluated = chunk % cfgs[0].eval_every_chunks == 0 or last
            if evaluated:
                for i, m in enumerate(members):
                    mine = member_runner(i)
                    val = stage.validate(mine)
                    history[i].append({"kind": "val", stage.step_name: step, **val})
                    if m.log:
                        m.log.write("val", step, val)
                    if stage.score(val) > stage.score(m.best):
                        m.best = {**{k: val[k] for k in stage.best_keys},
                                  stage.step_name: step}
                        m.ckpt.save(step, mine, {"chunk": chunk, "val": val}, best=True)
                stopped = stop(history) if stop is not None else None
                if stopped and primary:
                    bar.write(f"{stage.name}: stopped at {steps:,} {stage.unit}s, {stopped}",
                              file=sys.stderr)
                last = last or bool(stopped)
            # after this chunk's val evaluation, so the bar shows the last best_val
            bar.set_postfix(rate=f"{took * len(members) / dt:.0f}/s",
                            **{k: f"{np.mean(v):.3f}" for k, v in recent.items()},
                            best_val=f"{max(m.best[stage.score_keys[0]] for m in members):.3f}")
            if chunk % cfgs[0].checkpoint_every_chunks == 0 or last:
                for i, m in enumerate(members):
                    m.ckpt.save(step, member_runner(i), {"chunk": chunk, "best": m.best})
            if evaluated:
                marks.append((chunk, time.perf_counter()))
                if len(marks) == 2 and not last and not varying and primary:
                    bar.write(cycle_estimate(stage, marks, len(members), stop is not None),
                              file=sys.stderr)
            if (stop_after_chunks is not None and chunk >= stop_after_chunks and not last) or \
                    stopped:
                break
    finally:
        bar.close()
        for m in members:
            if m.log:
                m.log.close()
    wall = time.perf_counter() - t_start
    return [{"run_dir": str(m.run_dir), stage.step_name: steps,
             "chunks": chunk, "chunks_run": chunk - first_chunk, "best_val": m.best,
             "compile_plus_first_chunk_s": compile_s,
             "wall_s": wall, "stopped": stopped, "runner": member_runner(i)}
            for i, m in enumerate(members)]
