"""Stage 1, navigation training: the jitted A2C chunk on the host loop.

    result = train(cfg, resume=False)
    results = train_seeds(cfg, seeds=(0, 1, 2))     # one program, a run dir per seed

Each chunk is `cfg.updates_per_chunk` jitted updates (training/update.py); the host loop
(training/driver.py) logs, evaluates on the val episodes every `eval_every_chunks`
chunks keeping the best parameters, and saves the whole RunnerState every
`checkpoint_every_chunks`. With resume=True it continues from the latest checkpoint and
ends with the same parameters an uninterrupted run reaches (on the same machine).

With several devices (cfg.devices, training/scale.py) the env axis of the runner is
sharded over them and the parameters replicated; `train_seeds` trains several seeds of
one config as a population axis of one jitted chunk (vmap), each seed in its own run
directory `seed_run_dir(cfg.run_dir, seed)` = `<run_dir>-s<seed>`.
"""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path

import jax

from orgnav_jax import env, evaluation
from orgnav_jax.compile_cache import compiled_once, computation_of
from orgnav_jax.episodes import sample_episodes
from orgnav_jax.models import build_model
from orgnav_jax.training.config import TrainConfig, load_config
from orgnav_jax.errors import UserError
from orgnav_jax.training import savn, scale
from orgnav_jax.training.driver import (
    Stage, StopRule, run_population, run_stage)
from orgnav_jax.training.runs import (
    device_splits, keep_word_vectors, model_policy, preflight)
from orgnav_jax.training.update import init_runner, make_optimizer, make_train_chunk


# fields the jitted chunk does not read (compile_cache.py: runs differing only in these
# share one compiled program). The scene fields only say where the rooms come from: the
# rooms are the chunk's input (their shapes key jit's own cache) and their feature widths
# are in the model, so two copies of a set, or two sets of one shape, share the program.
HOST_ONLY_FIELDS = ("run_dir", "total_env_steps", "eval_every_chunks",
                    "eval_episodes_per_room_type", "checkpoint_every_chunks",
                    "keep_checkpoints", "seed", "devices",   # devices: the mesh is a key
                    "scene_preset", "scenes_dir", "scene_seed",
                    # VTNet's pre-training stage (training/pretrain.py)
                    "pretrain_samples", "pretrain_batch", "pretrain_lr",
                    "pretrain_weight_decay", "pretrain_lr_drop", "pretrain_clip",
                    "pretrain_val_samples")
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
    from orgnav_jax.training.checkpoints import RunCheckpoints
    if cfg.pretrained is None or (resume and RunCheckpoints(cfg.run_dir).latest_step()
                                  is not None):
        return runner
    from orgnav_jax.training.pretrain import load_pretrained
    return runner.replace(params=load_pretrained(cfg, runner.params))


@compiled_once
def cached_train_chunk(cfg: TrainConfig, model, mesh=None, population: bool = False):
    """(optimizer, jitted train chunk), shared by runs in one process that differ only in
    seed, budget or run directory (so they compile once); sharded over `mesh` (None: one
    device), vmapped over a seed axis if `population`."""
    optimizer = make_optimizer(cfg)
    return optimizer, make_train_chunk(cfg, model, optimizer, mesh=mesh,
                                       population=population)


def seed_run_dir(run_dir: str, seed: int) -> str:
    """The run directory of one seed of a population: <run_dir>-s<seed>."""
    return f"{str(run_dir).rstrip('/')}-s{seed}"


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


@compiled_once
def cached_savn_chunk(cfg: TrainConfig, model):
    """(optimizer, learned loss module, jitted SAVN chunk): shared as cached_train_chunk."""
    optimizer = make_optimizer(cfg)
    learned = savn.build_learned_loss()
    return optimizer, learned, savn.make_savn_chunk(cfg, model, learned, optimizer)


def savn_runner(cfg: TrainConfig, model, train_scenes):
    optimizer, learned, _ = cached_savn_chunk(compute_config(cfg), model)
    return savn.init_savn_runner(cfg, model, learned, optimizer, train_scenes,
                                 jax.random.PRNGKey(cfg.seed))


# Config versions whose SAVN runs cannot be resumed by this one (issue 40), each with why:
# (the first version that does it this way, what a run saved before it did).
SAVN_RESUME_BREAKS = (
    # the budget counts the env steps the episodes really took
    (7, "env_steps count episode slots (every episode at its cap); this version counts the "
        "env steps the episodes really took"),
    # the updates refill ended rows (training/savn.py: REFILL_VERSION)
    (savn.REFILL_VERSION, "updates stepped every episode whole to its cap; this version "
                          "refills ended rows at segment boundaries and carries running "
                          "episodes between updates"),
    # the rows' low-rank slots per LSTM layer (LAYERED_VERSION)
    (savn.LAYERED_VERSION, "checkpoints hold the running episodes' fast weights with only "
                           "the first LSTM layer's updates low-rank; this version keeps "
                           "every layer's low-rank"),
)


def check_savn_resume(run_dir) -> None:
    """UserError (one line) when run_dir holds a SAVN run of a config version before one
    of SAVN_RESUME_BREAKS (continuing it would mix two meanings of its count or read its
    checkpoints in the wrong layout); the first break it predates is named. Nothing to
    check without a config.json (a new run)."""
    import json
    path = Path(run_dir) / "config.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return                     # no saved run (or load_config reports the bad file)
    version = doc.get("version") if isinstance(doc, dict) else None
    if not isinstance(version, int) or doc.get("savn") is not True:
        return
    for since, why in SAVN_RESUME_BREAKS:
        if version < since:
            raise UserError(f"--resume {run_dir}: a SAVN run of config version {version}, "
                            f"whose {why} (issue 40): start a new run, or evaluate this one "
                            "as it is")


def savn_stage(cfg: TrainConfig, model, train_scenes, val_scenes, val_episodes) -> Stage:
    """Stage 1 in SAVN mode (training/savn.py): updates of num_envs rows x savn_segments
    segments with inner steps, ended rows refilled at segment boundaries; val with the
    test-time inner steps (savn_policy). The budget counts the env steps the episodes
    really took (the chunk's env_steps_real): the run stops after the first chunk whose
    running count reaches total_env_steps."""
    _, learned, chunk = cached_savn_chunk(compute_config(cfg), model)
    policy = savn.run_policy(cfg, model, val_scenes)
    return Stage(
        name=f"train {cfg.model}+savn", unit="step", step_name="env_steps",
        rate_key="steps_per_s",
        per_chunk=cfg.updates_per_chunk * cfg.steps_per_update,
        total=cfg.total_env_steps, steps_key="env_steps_real",
        chunk=lambda runner: chunk(runner, train_scenes), summarize=chunk_summary,
        validate=lambda runner: evaluation.evaluate(
            policy, runner.params, val_scenes, val_episodes,
            env.EnvParams.evaluation())["overall"],
        score_keys=("success", "spl"), best_keys=("spl", "success"),
        progress_keys=("success",))


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True,
          stop_after_chunks: int | None = None) -> dict:
    """Train (or resume) the run in cfg.run_dir -> summary dict (best val, env steps).
    stop_after_chunks ends early (for tests of kill-and-resume)."""
    if resume and cfg.savn:
        check_savn_resume(cfg.run_dir)
    cfg = keep_word_vectors(cfg, resume)     # the run keeps the sha256 of its vectors
    mesh = scale.make_mesh(cfg.devices)
    scale.check_batch(cfg.num_envs, mesh)
    # config ranges, scenes (their widths those of a resumed run's checkpoints), memory:
    # before anything is written
    scenes = preflight(cfg, resumed=[cfg.run_dir] if resume else [])
    if not resume:                # VTNet from a pre-training: that run, before any write
        from orgnav_jax.training.pretrain import check_pretrained
        check_pretrained(cfg, scenes)
    with scale.open_shared_run_dir(cfg.run_dir, cfg, resume, load_config) as run_dir:
        return _train([cfg], scenes, [run_dir], mesh, resume, progress,
                      stop_after_chunks)[0]


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
    if len(cfgs) == 1:
        return [train(cfgs[0], resume, progress, stop_after_chunks)]
    for c in cfgs:
        c.validate()
    cfgs = [keep_word_vectors(c, resume) for c in cfgs]
    mesh = scale.make_mesh(cfg.devices)
    scale.check_batch(cfg.num_envs, mesh)
    scenes = preflight(cfgs[0], resumed=[c.run_dir for c in cfgs] if resume else [])
    if not resume:
        from orgnav_jax.training.pretrain import check_pretrained
        for c in cfgs:
            check_pretrained(c, scenes)
    with contextlib.ExitStack() as stack:
        run_dirs = [stack.enter_context(scale.open_shared_run_dir(c.run_dir, c, resume,
                                                                  load_config))
                    for c in cfgs]
        return _train(cfgs, scenes, run_dirs, mesh, resume, progress, stop_after_chunks,
                      population=True, stop=stop)


def _train(cfgs: list[TrainConfig], scenes, run_dirs: list[Path], mesh, resume: bool,
           progress: bool, stop_after_chunks: int | None,
           population: bool = False, stop: StopRule | None = None) -> list[dict]:
    cfg = cfgs[0]
    # the train and val splits of the set preflight loaded, on the device; the test rooms
    # of the memory-mapped set are never read
    train_scenes, val_scenes = device_splits(scenes, "train", "val")
    val_episodes = sample_episodes(val_scenes, cfg.eval_episodes_per_room_type, seed=0,
                                   split="val")
    model = build_model(cfg, train_scenes)
    if cfg.savn:
        if population or mesh is not None:
            raise UserError("savn: one seed on one device per run (no --seeds population, "
                            "no --devices mesh yet; docs/savn.md)")
        return [run_stage(savn_stage(cfg, model, train_scenes, val_scenes, val_episodes),
                          savn_runner(cfg, model, train_scenes), cfg, run_dirs[0], resume,
                          progress, stop_after_chunks)]
    optimizer, train_chunk = cached_train_chunk(compute_config(cfg), model, mesh,
                                                population)
    runners = [start_from_pretrained(c, init_runner(c, model, optimizer, train_scenes,
                                                    jax.random.PRNGKey(c.seed)), resume)
               for c in cfgs]
    if mesh is None:
        chunk_scenes, place = train_scenes, (lambda runner: runner)
    else:        # the scene set replicated on every device; the env axis sharded
        chunk_scenes = scale.place(train_scenes, scale.replicated(train_scenes, mesh))
        place = lambda runner: scale.place(runner, scale.runner_shardings(runner, mesh,
                                                                         population))
    stage = Stage(
        name=f"train {cfg.model}", unit="step", step_name="env_steps", rate_key="steps_per_s",
        per_chunk=cfg.updates_per_chunk * cfg.steps_per_update,
        total=cfg.num_updates * cfg.steps_per_update,
        chunk=lambda runner: train_chunk(runner, chunk_scenes), summarize=chunk_summary,
        validate=lambda runner: evaluate_on_val(model, scale.local_copy(runner.params), val_scenes,
                                         val_episodes),
        score_keys=("success", "spl"), best_keys=("spl", "success"),
        progress_keys=("success",), place=place)
    if population:
        return run_population(stage, runners, cfgs, run_dirs, resume, progress,
                              stop_after_chunks, stop=stop)
    return [run_stage(stage, runners[0], cfg, run_dirs[0], resume, progress,
                      stop_after_chunks)]
