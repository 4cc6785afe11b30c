"""Stage 1, navigation training: the jitted A2C chunk on the host loop.

    result = train(cfg, resume=False)

Each chunk is `cfg.updates_per_chunk` jitted updates (training/update.py); the host loop
(training/driver.py) logs, evaluates on the val episodes every `eval_every_chunks`
chunks keeping the best parameters, and saves the whole RunnerState every
`checkpoint_every_chunks`. With resume=True it continues from the latest checkpoint and
ends with the same parameters an uninterrupted run reaches (on the same machine).
"""

from __future__ import annotations

from pathlib import Path

import jax

from orgnav_jax import env, evaluation
from orgnav_jax.compile_cache import compiled_once, computation_of
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.models import build_model
from orgnav_jax.training.config import TrainConfig, load_config
from orgnav_jax.training.driver import NonFiniteLoss, Stage, run_stage  # noqa: F401 (API)
from orgnav_jax.training.runs import model_policy, preflight, split_on_device
from orgnav_jax.training.run_dir import open_run_dir
from orgnav_jax.training.update import init_runner, make_optimizer, make_train_chunk


# fields the jitted chunk does not read (compile_cache.py: runs differing only in these
# share one compiled program)
HOST_ONLY_FIELDS = ("run_dir", "total_env_steps", "eval_every_chunks",
                    "eval_episodes_per_room_type", "checkpoint_every_chunks",
                    "keep_checkpoints", "seed")


def compute_config(cfg: TrainConfig) -> TrainConfig:
    """cfg without the fields that do not change the jitted computation."""
    return computation_of(cfg, HOST_ONLY_FIELDS)


@compiled_once
def cached_train_chunk(cfg: TrainConfig, model):
    """(optimizer, jitted train chunk), shared by runs in one process that differ only in
    seed, budget or run directory (so they compile once)."""
    optimizer = make_optimizer(cfg)
    return optimizer, make_train_chunk(cfg, model, optimizer)


def chunk_summary(m: dict) -> dict:
    """Per-chunk sums -> means (success, SPL, return, length per finished episode)."""
    out = {k: float(v) for k, v in m.items()}
    n = max(out.pop("episodes"), 1.0)
    for k in ("success", "spl", "ret", "length"):
        out[k] = out[k] / n
    out["episodes"] = n
    return out


def evaluate_on_val(model, params, val_scenes, val_episodes) -> dict:
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
    stage = Stage(
        name=f"train {cfg.model}", unit="step", step_name="env_steps", rate_key="steps_per_s",
        per_chunk=cfg.updates_per_chunk * cfg.steps_per_update,
        total=cfg.num_updates * cfg.steps_per_update,
        chunk=lambda runner: train_chunk(runner, train_scenes), summarize=chunk_summary,
        validate=lambda runner: evaluate_on_val(model, runner.params, val_scenes, val_episodes),
        score_keys=("success", "spl"), best_keys=("spl", "success"),
        progress_keys=("success",))
    return run_stage(stage, runner, cfg, run_dir, resume, progress, stop_after_chunks)
