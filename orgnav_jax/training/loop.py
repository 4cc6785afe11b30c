"""Stage 1, navigation training: the jitted A2C (or SAVN) chunk on the host loop.

    result = train(cfg, resume=False)
    results = train_seeds(cfg, seeds=(0, 1, 2))     # one program, a run dir per seed

One path for both: `train_runs` takes the configs (one run, or one per seed), runs the
one preflight (training/runs.py: every check before anything is written or compiled),
opens the run directories, builds the stage (`nav_stage`: A2C or SAVN) and runs it on
the shared host loop (training/driver.py).

Each chunk is `cfg.updates_per_chunk` jitted updates (training/update.py); the host loop
logs, evaluates on the val episodes every `eval_every_chunks` chunks keeping the best
parameters, and saves the whole RunnerState every `checkpoint_every_chunks`. With
resume=True it continues from the latest checkpoint and ends with the same parameters an
uninterrupted run reaches (on the same machine).

With several devices (cfg.devices, training/scale.py) the env axis of the runner is
sharded over them and the parameters replicated; `train_seeds` trains several seeds of
one config as a population axis of one jitted chunk (vmap), each seed in its own run
directory `seed_run_dir(cfg.run_dir, seed)` = `<run_dir>-s<seed>`.
"""

from __future__ import annotations

import contextlib
import dataclasses

import jax

from orgnav_jax import env, evaluation
from orgnav_jax.compile_cache import compiled_once, computation_of
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.errors import UserError
from orgnav_jax.models import build_model
from orgnav_jax.training import savn, scale
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.config import TrainConfig, load_config
from orgnav_jax.training.config_fields import host_only_fields
from orgnav_jax.training.driver import Stage, StopRule, run_population
from orgnav_jax.training.pretrain import load_pretrained
from orgnav_jax.training.run_dir import seed_run_dir
from orgnav_jax.training.runs import device_splits, model_policy, preflight
from orgnav_jax.training.update import init_runner, make_optimizer, make_train_chunk


# fields the jitted chunk does not read (compile_cache.py: runs differing only in these
# share one compiled program): marked host_only next to each field (training/config.py)
HOST_ONLY_FIELDS = host_only_fields(TrainConfig, "nav")
PRETRAINED = "(a pre-training run)"   # compute_config's `pretrained`: whether, not where


def compute_config(cfg: TrainConfig) -> TrainConfig:
    """cfg without the fields that do not change the jitted computation (`pretrained`:
    only whether there is one, for the optimiser's pretrained_lr_scale)."""
    cfg = computation_of(cfg, HOST_ONLY_FIELDS)
    return cfg if cfg.pretrained is None else dataclasses.replace(cfg, pretrained=PRETRAINED)


def start_from_pretrained(cfg: TrainConfig, runner, resume: bool):
    """The runner with the visual parameters of the pre-training run cfg.pretrained
    (VTNet: training/pretrain.py), unless a resume continues from a checkpoint (which
    holds them: the pre-training run is not read again)."""
    if cfg.pretrained is None or (resume and RunCheckpoints(cfg.run_dir).latest_step()
                                  is not None):
        return runner
    return runner.replace(params=load_pretrained(cfg, runner.params))


@compiled_once
def cached_train_chunk(cfg: TrainConfig, model, mesh=None, population: bool = False):
    """(optimizer, jitted train chunk), shared by runs in one process that differ only in
    seed, budget or run directory (so they compile once); sharded over `mesh` (None: one
    device), vmapped over a seed axis if `population`."""
    optimizer = make_optimizer(cfg)
    return optimizer, make_train_chunk(cfg, model, optimizer, mesh=mesh,
                                       population=population)


def chunk_summary(m: dict) -> dict:
    """Per-chunk sums -> means (success, SPL, return, length per finished episode)."""
    out = {k: float(v) for k, v in m.items()}
    n = max(out.pop("episodes"), 1.0)
    for k in ("success", "spl", "ret", "length"):
        out[k] = out[k] / n
    out["episodes"] = n
    return out


def evaluate_on_val(policy, params, val_scenes, val_episodes) -> dict:
    """The policy's evaluation on the val episodes -> overall metrics (A2C: greedy; SAVN:
    with its test-time inner steps and actions, savn.run_policy)."""
    return evaluation.evaluate(policy, params, val_scenes, val_episodes,
                               env.EnvParams.evaluation())["overall"]


@compiled_once
def cached_savn_chunk(cfg: TrainConfig, model):
    """(optimizer, learned loss module, jitted SAVN chunk): shared as cached_train_chunk."""
    optimizer = make_optimizer(cfg)
    learned = savn.build_learned_loss()
    return optimizer, learned, savn.make_savn_chunk(cfg, model, learned, optimizer)


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          stop_after_chunks: int | None = None, stop: StopRule | None = None) -> dict:
    """Train (or resume) the run in cfg.run_dir -> summary dict (best val, env steps).
    stop_after_chunks ends early (for tests of kill-and-resume); `stop` see train_seeds."""
    return train_runs([cfg], resume, progress, stop_after_chunks, stop)[0]


def train_seeds(cfg: TrainConfig, seeds, resume: bool = False, progress: bool = True,
                stop_after_chunks: int | None = None,
                stop: StopRule | None = None) -> list[dict]:
    """Train (or resume) cfg with each of `seeds` in one program (a vmapped population
    axis), seed s in seed_run_dir(cfg.run_dir, s) -> one summary per seed. One seed is
    an ordinary run (in its -s<seed> directory). A VTNet starting from pre-training
    (cfg.pretrained) starts seed s from seed_run_dir(cfg.pretrained, s). `stop`: a stop
    criterion on the seeds' val records (training/driver.py: run_population); the budget
    is then the cap."""
    seeds = [int(s) for s in seeds]
    if not seeds or len(set(seeds)) != len(seeds):
        raise UserError(f"--seeds {' '.join(map(str, seeds))}: expected distinct seeds")
    # a VTNet pre-training per seed: <pretrained>-s<seed>, as the run directories
    cfgs = [dataclasses.replace(cfg, seed=s, run_dir=seed_run_dir(cfg.run_dir, s),
                                pretrained=cfg.pretrained and seed_run_dir(cfg.pretrained, s))
            for s in seeds]
    return train_runs(cfgs, resume, progress, stop_after_chunks, stop)


def train_runs(cfgs: list[TrainConfig], resume: bool, progress: bool,
               stop_after_chunks: int | None, stop: StopRule | None) -> list[dict]:
    """Stage 1's one path: the preflight, the run directories opened (checked and
    locked), the stage built and run -> one summary per config. Several configs (the
    seeds of train_seeds) train as a population in one program."""
    cfgs, scenes, mesh = preflight(cfgs, resume)          # before anything is written
    with contextlib.ExitStack() as stack:
        run_dirs = [stack.enter_context(scale.open_shared_run_dir(c.run_dir, c, resume,
                                                                  load_config))
                    for c in cfgs]
        stage, runners = nav_stage(cfgs, scenes, mesh, resume)
        return run_population(stage, runners, cfgs, run_dirs, resume, progress,
                              stop_after_chunks, stacked=len(cfgs) > 1, stop=stop)


def stage_label(cfg: TrainConfig) -> str:
    """The progress label of a navigation run: its model, and what trains it besides A2C
    (e.g. "train baseline+il" for the IL row, "train we+savn" for SAVN)."""
    return (f"train {cfg.model}" + ("+il" if cfg.il != "none" else "")
            + ("+savn" if cfg.savn else ""))


def nav_stage(cfgs: list[TrainConfig], scenes, mesh, resume: bool) -> tuple[Stage, list]:
    """Stage 1 as the host loop's Stage, and one runner per config (several: a population,
    the chunk vmapped over the stacked runners), on the train and val splits of the
    SceneSet preflight loaded (the test rooms of the memory-mapped set are never read).

    A2C (training/update.py): the budget is whole updates of num_envs x rollout_len env
    steps; with a mesh the env axis is sharded over its devices, the scenes replicated.
    SAVN (cfg.savn, training/savn.py): updates of num_envs rows x savn_segments segments
    with inner steps, ended rows refilled at segment boundaries; val with the test-time
    inner steps (savn.run_policy). Its budget counts the env steps the episodes really
    took (the chunk's env_steps_real): the run stops after the first chunk whose running
    count reaches total_env_steps."""
    cfg = cfgs[0]
    train_scenes, val_scenes = device_splits(scenes, "train", "val")
    val_episodes = sample_episodes(val_scenes, cfg.eval_episodes_per_room_type, seed=0,
                                   split="val")
    model = build_model(cfg, train_scenes)
    chunk_scenes, place = train_scenes, (lambda runner: runner)
    if cfg.savn:
        optimizer, learned, chunk = cached_savn_chunk(compute_config(cfg), model)
        runners = [savn.init_savn_runner(c, model, learned, optimizer, train_scenes,
                                         jax.random.PRNGKey(c.seed)) for c in cfgs]
        policy = savn.run_policy(cfg, model, val_scenes)
    else:
        optimizer, chunk = cached_train_chunk(compute_config(cfg), model, mesh,
                                              len(cfgs) > 1)
        runners = [start_from_pretrained(c, init_runner(c, model, optimizer, train_scenes,
                                                        jax.random.PRNGKey(c.seed)), resume)
                   for c in cfgs]
        policy = model_policy(model)
        if mesh is not None:    # the scene set replicated on every device; the env axis
            chunk_scenes = scale.place(train_scenes, scale.replicated(train_scenes, mesh))
            place = lambda runner: scale.place(runner, scale.runner_shardings(  # sharded
                runner, mesh, len(cfgs) > 1))
    stage = Stage(
        name=stage_label(cfg), unit="step",
        step_name="env_steps", rate_key="steps_per_s",
        per_chunk=cfg.updates_per_chunk * cfg.steps_per_update,
        total=cfg.total_env_steps if cfg.savn else cfg.num_updates * cfg.steps_per_update,
        steps_key="env_steps_real" if cfg.savn else None,
        chunk=lambda runner: chunk(runner, chunk_scenes), summarize=chunk_summary,
        validate=lambda runner: evaluate_on_val(policy, scale.local_copy(runner.params),
                                                val_scenes, val_episodes),
        score_keys=("success", "spl"), best_keys=("spl", "success"),
        progress_keys=("success",), place=place)
    return stage, runners
