"""Checkpoints with orbax: the whole RunnerState plus a JSON of config and progress.

Layout of a run directory:
    checkpoints/<step>/  the latest runs (orbax; a save is written to a temporary
                         directory and renamed when complete, so an interrupted save
                         leaves the previous checkpoint loadable)
    best/<step>/         the best-on-val parameters
    broken_checkpoints/  latest-N checkpoints that could not be read on resume
(config.json, the lock and the logs: training/run_dir.py)
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import sys
import threading
import traceback
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from orgnav_jax.errors import (
    field_error, is_int, is_number, read_field, read_int, read_object, shown,
)
from orgnav_jax.models.navmodel import check_feature_widths, feature_widths
from orgnav_jax.training.config_fields import CONFIG_VERSION, READABLE_VERSIONS

logging.getLogger("absl").setLevel(logging.ERROR)


def _manager(path: Path, keep: int) -> ocp.CheckpointManager:
    """create=False: a read makes no folder (a save still makes its own)."""
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=False,
                                           enable_async_checkpointing=False)
    handlers = {"state": ocp.StandardCheckpointHandler(), "meta": ocp.JsonCheckpointHandler()}
    return ocp.CheckpointManager(path.absolute(), options=options, item_handlers=handlers)


def _leaf_shapes(tree) -> dict[str, tuple]:
    """{'params/trunk/actor/kernel': (shape, dtype)} for arrays or array metadata."""
    def name(path):
        return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k))))
                        for k in path)
    return {name(p): (tuple(x.shape), str(x.dtype))
            for p, x in jax.tree_util.tree_leaves_with_path(tree)}


def _mismatch(saved, wanted) -> str | None:
    """The first difference between a checkpoint's and a model's arrays, in words."""
    have, want = _leaf_shapes(saved), _leaf_shapes(wanted)
    for key in sorted(set(have) | set(want)):
        if key not in have:
            return f"{key} is missing from the checkpoint"
        if key not in want:
            return f"the checkpoint has {key}, which this model lacks"
        if have[key] != want[key]:
            return f"{key} is {have[key][0]} {have[key][1]} in the checkpoint, " \
                   f"{want[key][0]} {want[key][1]} in this model"
    return None


class RunCheckpoints:
    """The latest-N and best-on-val checkpoint managers of a run directory."""

    def __init__(self, run_dir: str | os.PathLike, keep: int = 2):
        self.run_dir, self.keep = Path(run_dir), keep
        self.latest = _manager(self.run_dir / "checkpoints", keep)
        self.best = _manager(self.run_dir / "best", 1)

    def save(self, step: int, runner, meta: dict, best: bool = False) -> None:
        meta = dict(meta, config_version=CONFIG_VERSION)
        manager = self.best if best else self.latest
        state = runner.params if best else runner
        manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                   meta=ocp.args.JsonSave(meta)), force=True)
        manager.wait_until_finished()

    def drop_best_after(self, step: int) -> None:
        """A resume from `step` retraces the steps after it: a best-on-val checkpoint
        saved after it belongs to the discarded part and is saved again when reached."""
        for s in self.best.all_steps():
            if s > step:
                self.best.delete(s)

    def latest_step(self) -> int | None:
        return self.latest.latest_step()

    def feature_widths(self, best: bool = False) -> dict[str, int]:
        """The scene feature widths the newest (or best) checkpoint's model was built
        for, from its array metadata (no array is read): models.feature_widths. {} when
        there is no checkpoint or its metadata cannot be read (restore names that)."""
        manager = self.best if best else self.latest
        step = manager.latest_step()
        if step is None:
            return {}
        try:
            return feature_widths(manager.item_metadata(step)["state"])
        except Exception:                   # orbax raises many kinds; restore reports it
            return {}

    def check_scenes(self, scenes, scenes_name: str, best: bool = False) -> None:
        """ValueError (one line) when `scenes`' feature widths differ from those the
        newest (or best) checkpoint was trained on: before any model is built."""
        step = (self.best if best else self.latest).latest_step()
        where = f"checkpoint {self.run_dir / ('best' if best else 'checkpoints') / str(step)}"
        check_feature_widths(self.feature_widths(best), scenes, where, scenes_name)

    def restore(self, like, best: bool = False, step: int | None = None,
                fallback: bool = False):
        """-> (state shaped like `like`, meta dict), from the newest checkpoint (or `best`,
        or `step`). Clear errors for a checkpoint from another model or version. With
        fallback=True (a resume) the newest readable one of the latest-N wins: broken
        newer ones are named on stderr and moved to broken_checkpoints/ (never deleted);
        if none can be read, the newest one's error is raised and nothing is moved."""
        manager = self.best if best else self.latest
        if best or step is not None or not fallback:
            step = manager.latest_step() if step is None else step
            if step is None:
                raise FileNotFoundError(f"no {'best ' if best else ''}checkpoint in "
                                        f"{self.run_dir}")
            return _restore_one(manager, step, like)
        steps = sorted(manager.all_steps(), reverse=True)
        if not steps:
            raise FileNotFoundError(f"no checkpoint in {self.run_dir}/checkpoints")
        broken = []
        for s in steps:
            try:
                with _quiet_failed_reads():
                    out = _restore_one(manager, s, like)
            except CheckpointUnreadable as err:
                broken.append((s, err))
                continue
            for bad, err in broken:
                aside = _set_aside(self.run_dir, Path(manager.directory) / str(bad))
                print(f"warning: {err}; moved it to {aside} and resumed from step {s}",
                      file=sys.stderr, flush=True)
            if broken:       # the manager rescans the directory
                self.latest = _manager(self.run_dir / "checkpoints", self.keep)
            return out
        raise broken[0][1]


@contextlib.contextmanager
def _quiet_failed_reads():
    """While trying a checkpoint that may be damaged: orbax's reader threads and
    coroutines die with it and Python would print each one's traceback ("Event loop is
    closed", "Exception ignored in <coroutine _read_array_index...>"). The error that
    matters is raised and named by restore; those echoes are dropped: all of them during
    the attempt, and afterwards (coroutines are collected later) those whose traceback
    runs through orbax or whose message is the closed event loop (_drop_read_echoes)."""
    hooks = sys.unraisablehook, threading.excepthook
    log = logging.getLogger("asyncio")
    level = log.level
    sys.unraisablehook = threading.excepthook = lambda *_: None
    log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        gc.collect()
        sys.unraisablehook, threading.excepthook = hooks
        log.setLevel(level)
        _drop_read_echoes()


def _is_read_echo(exc: BaseException | None, tb, obj=None) -> bool:
    """Whether an exception comes from orbax reading a damaged checkpoint: orbax in its
    traceback, or tensorstore's error for a checkpoint's OCDBT database (a read future
    has no Python traceback), or the closed event loop the reads report."""
    text = f"{obj!r} {exc!r} " + "".join(traceback.format_tb(tb)) if tb else f"{obj!r} {exc!r}"
    return any(mark in text for mark in ("orbax", "_read_array_index", "in OCDBT database",
                                         "Event loop is closed"))


def _drop_read_echoes() -> None:
    """Process-wide, once: unraisable and thread exceptions from orbax's reads (and the
    closed event loop they report), and the asyncio logger's records of its dead tasks,
    are dropped; every other one reaches the hooks and handlers installed before."""
    if getattr(sys.unraisablehook, "_orgnav_read_echoes", False):
        return
    unraisable, thread_hook = sys.unraisablehook, threading.excepthook

    def on_unraisable(u):
        if not _is_read_echo(u.exc_value, u.exc_traceback, u.object):
            unraisable(u)

    def on_thread(args):
        if not _is_read_echo(args.exc_value, args.exc_traceback):
            thread_hook(args)

    on_unraisable._orgnav_read_echoes = True
    sys.unraisablehook, threading.excepthook = on_unraisable, on_thread
    logging.getLogger("asyncio").addFilter(_not_a_read_echo)


def _not_a_read_echo(record: logging.LogRecord) -> bool:
    """The asyncio logger's filter: a task or future of orbax's reads that died with the
    damaged checkpoint and is collected later ("Task/Future exception was never
    retrieved") is dropped."""
    exc, tb = record.exc_info[1:] if record.exc_info else (None, None)
    return not _is_read_echo(exc, tb, record.getMessage())


class CheckpointUnreadable(ValueError):
    """A checkpoint that does not fit the model or cannot be read."""


def _abstract(x):
    """A leaf of `like` as the ShapeDtypeStruct to restore into: its own sharding, or
    (shapes only, e.g. from jax.eval_shape) this process's first device. Checkpoints
    hold global arrays, so one saved on a mesh of other devices restores here; a run on
    a mesh puts the restored runner on it afterwards (training/scale.py)."""
    x = ocp.utils.to_shape_dtype_struct(x)
    if getattr(x, "sharding", None) is None:
        x = jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=jax.sharding.SingleDeviceSharding(
            jax.local_devices()[0]))
    return x


def _restore_one(manager, step: int, like):
    where = f"checkpoint {manager.directory}/{step}"
    abstract = jax.tree_util.tree_map(_abstract, like)
    try:
        problem = _mismatch(manager.item_metadata(step)["state"], abstract)
    except Exception as err:                        # orbax raises many kinds
        raise CheckpointUnreadable(f"{where} cannot be read ({_short(err)})") from None
    if problem:      # checked before any read, so no restore is left half done
        raise CheckpointUnreadable(f"{where} does not fit this model and config (another "
                                   f"model or widths, or damaged metadata?): {problem}")
    try:
        out = manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()))
    except Exception as err:
        raise CheckpointUnreadable(f"{where} cannot be read ({_short(err)})") from None
    return out["state"], read_meta(out["meta"], where, best=manager_is_best(manager))


def manager_is_best(manager) -> bool:
    return Path(manager.directory).name == "best"


def read_meta(meta, where: str, best: bool = False) -> dict:
    """The typed reader of a checkpoint's metadata (saved by RunCheckpoints.save):
    {"config_version": one of READABLE_VERSIONS, "chunk": int32 >= 0, and "best" (a
    latest-N checkpoint: the best val record so far) or "val" (a best-on-val one: its
    val record), each an object of numbers (nan allowed: a mean over no episodes)}.
    CheckpointUnreadable naming the checkpoint and the field otherwise (the chunk's
    range against the run is checked on resume: training/driver.py, resumed_chunk)."""
    if not isinstance(meta, dict):
        raise CheckpointUnreadable(f"{where}: its metadata is {shown(meta)}, expected a JSON "
                                   "object {config_version, chunk, best or val}")
    version = meta.get("config_version")
    if not is_int(version) or version not in READABLE_VERSIONS:
        raise CheckpointUnreadable(f"{where} has config version {shown(version)}, expected "
                                   f"one of {list(READABLE_VERSIONS)}")
    try:
        read_int(meta, "chunk", f"{where} metadata")
        record = "val" if best else "best"
        values = read_object(read_field(meta, record, f"{where} metadata"),
                             f"{where} metadata field {record!r}",
                             "an object of numbers (val metric -> value)")
        for key, value in values.items():      # nan: a mean over no episodes
            if not (is_number(value) or isinstance(value, float) and value != value):
                raise field_error(f"{where} metadata {record!r}", key, "a number", value)
    except ValueError as err:
        raise CheckpointUnreadable(str(err)) from None
    return meta


def _short(err: BaseException, limit: int = 160) -> str:
    text = " ".join(str(err).split()) or type(err).__name__
    return f"{type(err).__name__}: {text[:limit]}{'...' if len(text) > limit else ''}"


def _set_aside(run_dir: Path, step_dir: Path) -> Path:
    """Move a broken checkpoint to run_dir/broken_checkpoints/<step>[.k]."""
    target = run_dir / "broken_checkpoints" / step_dir.name
    target.parent.mkdir(exist_ok=True)
    k = 0
    while target.exists():
        k += 1
        target = target.with_name(f"{step_dir.name}.{k}")
    os.rename(step_dir, target)
    return target
