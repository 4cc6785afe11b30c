"""Shared by the test modules and tests/scale_worker.py (a subprocess script): the small
run every trainer test uses, a chunk that reports a non-finite loss, the trained-vs-random check of the learning tests, and a
results JSON made from per-episode success flags.
(pytest puts tests/ on sys.path: `from helpers import ...`.)"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

CHUNK = 16 * 8 * 2          # env steps per chunk of small runs
EXPERIMENTS = Path(__file__).resolve().parents[1] / "experiments"


def experiment_script(name: str):
    """experiments/<name>.py loaded as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(name, EXPERIMENTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def small_options(scenes_dir, run_dir, **kw) -> dict:
    """A few-second run on the tiny scenes: 4 chunks of 2 updates of 16 envs x 8 steps,
    val every 2 chunks, a checkpoint every chunk -> TrainConfig fields (kw override)."""
    return dict(dict(scenes_dir=str(scenes_dir), num_envs=16, rollout_len=8,
                     updates_per_chunk=2, total_env_steps=4 * CHUNK, eval_every_chunks=2,
                     eval_episodes_per_room_type=4, checkpoint_every_chunks=1,
                     run_dir=str(run_dir)), **kw)


def small_cfg(scenes_dir, run_dir, **kw):
    """The TrainConfig of small_options on the tiny preset."""
    from orgnav_jax.training.config import get_config
    return get_config("tiny", **small_options(scenes_dir, run_dir, **kw))


def poison_chunk(monkeypatch, at: int, nan_params: bool = False) -> None:
    """Make the trainer's chunk number `at` (1-based, counted from the next call) report a
    non-finite loss, and with nan_params also return NaN parameters. The cached chunk is
    wrapped, not cleared: other tests keep its compile."""
    import jax
    import jax.numpy as jnp
    from orgnav_jax.training import loop
    real = loop.cached_train_chunk

    def poisoned(*args, **kw):
        optimizer, chunk_fn = real(*args, **kw)
        calls = [0]

        def wrapped(runner, scenes):
            calls[0] += 1
            runner, metrics = chunk_fn(runner, scenes)
            if calls[0] != at:
                return runner, metrics
            if nan_params:
                runner = runner.replace(params=jax.tree_util.tree_map(
                    lambda x: x * jnp.nan, runner.params))
            return runner, dict(metrics, loss_finite=jnp.bool_(False))
        return optimizer, wrapped
    monkeypatch.setattr(loop, "cached_train_chunk", poisoned)


def trained_and_random_success(run_dir, scenes_dir, split: str) -> tuple[float, float]:
    """Success of a run's latest model and of the random policy on the same seeded
    episodes of a split (the learning tests' comparison, fixed seeds)."""
    from orgnav_jax import episodes, evaluation, scenes
    from orgnav_jax.training.runs import load_run_policy
    policy, params, _ = load_run_policy(run_dir, best=False)
    rooms = scenes.load(scenes_dir).split_view(split).to_device()
    eps = episodes.sample_episodes(rooms, seed=0, split=split)
    trained = evaluation.evaluate(policy, params, rooms, eps)["overall"]["success"]
    rand = evaluation.evaluate(evaluation.random_policy(), None, rooms, eps,
                               seed=0)["overall"]["success"]
    return trained, rand


def fake_results(success: np.ndarray, rng) -> dict:
    """A results JSON as api.evaluate writes it, from per-episode success flags."""
    from orgnav_jax.evaluation import episode_record, metrics
    e = len(success)
    optimal = rng.integers(1, 12, e)
    path = optimal + rng.integers(0, 8, e)
    timeout = ~success & (rng.random(e) < 0.5)
    per = {"success": success, "wrong_done": ~success & ~timeout, "timeout": timeout,
           "path_len": path, "optimal_len": optimal, "revisits": rng.integers(0, 5, e),
           "failed_moves": rng.integers(0, 3, e), "room_type": np.arange(e) % 4,
           "target": np.arange(e) % 22}
    per["spl"] = success * optimal / np.maximum(path, optimal)
    return dict(metrics(per), per_episode=episode_record(per))
