"""Checkpoints with orbax: the whole RunnerState plus a JSON of config and progress.

Layout of a run directory:
    config.json          the TrainConfig (written once, atomically)
    checkpoints/<step>/  the latest runs (orbax; a save is written to a temporary
                         directory and renamed when complete, so an interrupted save
                         leaves the previous checkpoint loadable)
    best/<step>/         the best-on-val parameters
    metrics.jsonl, tb/   logs
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from orgnav_jax.training.config import CONFIG_VERSION, READABLE_VERSIONS, TrainConfig

logging.getLogger("absl").setLevel(logging.ERROR)


def _manager(path: Path, keep: int) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=True,
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
        self.run_dir = Path(run_dir)
        self.latest = _manager(self.run_dir / "checkpoints", keep)
        self.best = _manager(self.run_dir / "best", 1)

    def save(self, step: int, runner, meta: dict, best: bool = False) -> None:
        meta = dict(meta, config_version=CONFIG_VERSION)
        manager = self.best if best else self.latest
        state = runner.params if best else runner
        manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                   meta=ocp.args.JsonSave(meta)), force=True)
        manager.wait_until_finished()

    def latest_step(self) -> int | None:
        return self.latest.latest_step()

    def restore(self, like, best: bool = False, step: int | None = None):
        """-> (state shaped like `like`, meta dict). Clear errors for a checkpoint from
        another model or version."""
        manager = self.best if best else self.latest
        step = manager.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no {'best' if best else ''} checkpoint in {self.run_dir}")
        abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, like)
        problem = _mismatch(manager.item_metadata(step)["state"], abstract)
        if problem:      # checked before any read, so no restore is left half done
            raise ValueError(f"checkpoint {manager.directory}/{step} does not fit this model "
                             f"and config (another model or widths?): {problem}")
        out = manager.restore(step, args=ocp.args.Composite(
            state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()))
        meta = out["meta"]
        if meta.get("config_version") not in READABLE_VERSIONS:
            raise ValueError(f"checkpoint {manager.directory}/{step} has config version "
                             f"{meta.get('config_version')}, expected one of "
                             f"{list(READABLE_VERSIONS)}")
        return out["state"], meta


def has_checkpoints(run_dir: str | os.PathLike) -> bool:
    """Whether a run directory holds at least one latest-N checkpoint."""
    path = Path(run_dir) / "checkpoints"
    return path.exists() and any(path.iterdir())


BUDGET_FIELDS = ("total_env_steps", "total_episodes")   # a resume may extend these


def check_run_dir(run_dir: str | os.PathLike, cfg, resume: bool, load_saved) -> None:
    """Before a run starts: --resume needs the saved config (load_saved(run_dir)) to equal
    cfg, except that the budget may grow (the run continues to the larger budget; it
    matches a run started with that budget when the old budget ended on an evaluation
    and checkpoint chunk); a fresh run must not overwrite checkpoints."""
    if resume:
        saved = load_saved(run_dir)
        budget = {f: getattr(cfg, f) for f in BUDGET_FIELDS if hasattr(cfg, f)}
        if dataclasses.replace(saved, **budget) != cfg:
            raise ValueError(f"--resume: {run_dir}/config.json differs from the requested "
                             "config; resume with the same options (or none)")
        for f, value in budget.items():
            if value < getattr(saved, f):
                raise ValueError(f"--resume: {f} {value} is below the run's "
                                 f"{getattr(saved, f)}; a resume may only extend the budget")
    elif has_checkpoints(run_dir):
        raise FileExistsError(f"{run_dir} already holds checkpoints: pass --resume to "
                              "continue it, or choose another --run-dir")


def write_config(run_dir: str | os.PathLike, cfg: TrainConfig) -> None:
    path = Path(run_dir) / "config.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name("config.json.tmp")
    tmp.write_text(cfg.to_json())
    os.replace(tmp, path)
