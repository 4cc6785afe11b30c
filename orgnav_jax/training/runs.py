"""What a training run needs and gives: stage 1's one preflight (every check before a
run writes or compiles anything: `preflight`), its scenes (scenes_for), its model and
params (load_run_model), and the model as a greedy evaluation Policy.

    cfgs, scenes, mesh = preflight([cfg], resume)     # stage 1 (training/loop.py)
    scenes = checked_scenes(cfg, resumed)             # the scenes' part (pre-training too)
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from orgnav_jax.compile_cache import compiled_once
from orgnav_jax.constants import split_index
from orgnav_jax.errors import UserError
from orgnav_jax.evaluation import Policy
from orgnav_jax.models import build_model, init_params, model_inputs, reset_carry
from orgnav_jax.models.word_vectors import category_table
from orgnav_jax.scenes import load_scenes
from orgnav_jax.training import savn, scale
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.config import (
    SAVN_ACTS, TrainConfig, load_config, load_pretrain_config)
from orgnav_jax.training.memory import check_memory
from orgnav_jax.training.run_dir import is_run_dir
from orgnav_jax.training.update import init_runner, make_optimizer


def preflight(cfgs: list[TrainConfig], resume: bool = False):
    """Every check before stage 1 writes or compiles anything, for one run or a
    population (one config per seed, trained in one program) -> (the configs with the
    sha256 of their word vectors, the SceneSet they train on, the device mesh). In order:
    each config's own validation (TrainConfig.validate), where it runs (SAVN: one seed on
    one device; num_envs over the mesh's devices), the run directories' (a resumed SAVN
    run of an older config version; the word vectors a run keeps), the scenes'
    (checked_scenes: train and val rooms, a resumed run's feature widths, the memory
    estimate), and the pre-training a VTNet starts from (check_pretrained). One-line
    errors (UserError, ValueError, OSError) naming the field, file or directory."""
    for c in cfgs:
        c.validate()
    cfg = cfgs[0]
    mesh = scale.make_mesh(cfg.devices)
    if cfg.savn and (len(cfgs) > 1 or mesh is not None):
        raise UserError("savn: one seed on one device per run (no --seeds population, "
                        "no --devices mesh yet; docs/savn.md)")
    scale.check_batch(cfg.num_envs, mesh)
    if resume and cfg.savn:
        check_savn_resume(cfg.run_dir)
    cfgs = [keep_word_vectors(c, resume) for c in cfgs]   # the sha256 the runs keep
    scenes = checked_scenes(cfgs[0], resumed=[c.run_dir for c in cfgs] if resume else [])
    if not resume:                # VTNet from a pre-training: that run, before any write
        for c in cfgs:
            check_pretrained(c, scenes)
    return cfgs, scenes, mesh


def checked_scenes(cfg: TrainConfig, resumed=()):
    """The SceneSet cfg trains on (memory-mapped), checked before a run writes or compiles
    anything: cfg's word-vector file, train and val rooms in the scenes, the scenes'
    feature widths those the checkpoints of the `resumed` run directories were trained on
    (before any model is built), and one jitted chunk's memory estimate against the
    memory available (training.memory.check_memory)."""
    check_word_vectors(cfg, "--word-vectors-sha256")   # a missing or malformed file, or
    scenes = scenes_for(cfg)                         # other vectors: one line
    check_training_scenes(scenes, cfg)
    for run_dir in resumed:
        if (Path(run_dir) / "checkpoints").is_dir():     # nothing is created elsewhere
            RunCheckpoints(run_dir).check_scenes(scenes, scenes_name(cfg))
    check_memory(cfg, scenes)
    return scenes


# the fields that shape (or change) the pre-trained network: a run starting from a
# pre-training must have the same
VISUAL_FIELDS = ("vtnet_dim", "vtnet_heads", "vtnet_ffn", "vtnet_encoder_layers",
                 "vtnet_decoder_layers", "vtnet_mask", "fuse_channels")


def check_pretrained(cfg: TrainConfig, scenes=None) -> None:
    """Before a run that starts from cfg.pretrained writes anything: that directory holds
    a VTNet pre-training with a best-on-val checkpoint, of cfg's VTNet widths (and of
    `scenes`' feature widths, if given); UserError / ValueError in one line otherwise."""
    if cfg.pretrained is None:
        return
    pre = load_pretrain_config(cfg.pretrained)
    differ = [f"{f} {getattr(pre, f)!r} (this run: {getattr(cfg, f)!r})"
              for f in VISUAL_FIELDS if getattr(pre, f) != getattr(cfg, f)]
    if differ:
        raise UserError(f"--pretrained {cfg.pretrained}: pre-trained with "
                        f"{', '.join(differ)}: pre-train with this run's VTNet fields")
    ckpt = RunCheckpoints(cfg.pretrained)
    if ckpt.best.latest_step() is None:
        raise UserError(f"--pretrained {cfg.pretrained}: no best-on-val checkpoint (the "
                        "pre-training has not reached its first val evaluation)")
    if scenes is not None:
        ckpt.check_scenes(scenes, scenes_name(cfg), best=True)


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


@compiled_once
def model_policy(model, name: str = "Model", box_scale: float = 1.0) -> Policy:
    """Greedy (argmax) actions of a NavModel; the LSTM carry resets at episode starts.
    policy_params are the model's variables. box_scale multiplies the boxes the model
    reads (the release's models read pixel boxes: models/release.py)."""
    def init(batch, params):
        return model.initial_carry(batch)

    def act(params, carry, obs, key, scenes, fresh):
        carry = reset_carry(carry, fresh)
        inputs = model_inputs(scenes, obs)
        if box_scale != 1.0:
            inputs = inputs._replace(box=inputs.box * box_scale)
        logits, _, carry, _ = model.apply(params, inputs, carry)
        return jnp.argmax(logits, -1).astype(jnp.int32), carry

    return Policy(name, init, act)


def scenes_for(cfg: TrainConfig):
    """The full SceneSet a config trains on (cached preset or a saved directory),
    memory-mapped: nothing of it is read until a split view is used (scenes/synthetic/cache.py; the
    last one loaded is kept)."""
    return load_scenes(cfg.scene_preset, cfg.scene_seed, cfg.scenes_dir)


def device_splits(scenes, *splits: str) -> tuple:
    """The given splits of a loaded (memory-mapped) SceneSet on the device, in order:
    what preflight loaded is what trains (only those splits' rooms are read)."""
    return tuple(scenes.split_view(split).to_device() for split in splits)


def scenes_name(cfg: TrainConfig) -> str:
    """The scene set a config names, in words (for messages)."""
    return cfg.scenes_dir or f"of preset {cfg.scene_preset!r} (seed {cfg.scene_seed})"


def check_training_scenes(scenes, cfg: TrainConfig) -> None:
    """Training needs train rooms to learn on and val rooms to select the best checkpoint
    (SceneSet.split); ValueError naming the scene set otherwise."""
    split = np.asarray(scenes.split)
    for name, why in (("train", "to learn on"), ("val", "to select the best checkpoint")):
        if not (split == split_index(name)).any():
            raise ValueError(f"scenes {scenes_name(cfg)} have no {name} rooms (split field): "
                             f"training needs {name} rooms {why}")


def check_word_vectors(cfg: TrainConfig, whose: str) -> str | None:
    """The sha256 of the word vectors cfg.word_vectors holds now (None without a file);
    ValueError naming the file when it is missing or malformed, or when cfg keeps a
    sha256 (word_vectors_sha256: `whose`, e.g. the run that was trained with it) that is
    not theirs: a run is never evaluated or resumed with other vectors than its own."""
    if not cfg.word_vectors:
        return None
    table = category_table(cfg.word_vectors)
    kept = cfg.word_vectors_sha256
    if kept is not None and kept != table.sha256:
        raise ValueError(f"word vectors {cfg.word_vectors}: not the vectors of {whose} "
                         f"(sha256 {table.sha256[:12]}..., expected {kept[:12]}...): the file "
                         "was changed or replaced; give the vectors the run was trained "
                         "with")
    return table.sha256


def keep_word_vectors(cfg: TrainConfig, resume: bool = False) -> TrainConfig:
    """cfg with the sha256 of its word vectors (kept in the run's config.json): a fresh
    run records the vectors it reads; a resumed run's saved sha256 must be that of the
    file now (ValueError naming the file otherwise). A run saved before the sha256 was
    kept resumes without it (nothing to compare)."""
    if not cfg.word_vectors:
        return cfg
    whose = f"the run {cfg.run_dir}" if resume else "--word-vectors-sha256"
    if cfg.word_vectors_sha256 is None and resume:
        if not is_run_dir(cfg.run_dir):
            return cfg                   # check_run_dir: "holds no run"
        kept = load_config(cfg.run_dir).word_vectors_sha256
        if kept is None:
            return cfg
        cfg = dataclasses.replace(cfg, word_vectors_sha256=kept)
    return dataclasses.replace(cfg, word_vectors_sha256=check_word_vectors(cfg, whose))


def _saved_version(run_dir) -> int:
    """The config version a run directory was saved with (its config.json was read and
    checked by load_config before)."""
    return int(json.loads((Path(run_dir) / "config.json").read_text())["version"])


def load_run_model(run_dir: str | Path, best: bool = True):
    """-> (NavModel, params, config) of a training run (its best-on-val checkpoint, else
    the latest); its scenes' feature widths must be those the checkpoint was trained on
    (checked before the model is built)."""
    cfg = load_config(run_dir)
    check_word_vectors(cfg, f"the run {run_dir}")       # the vectors it was trained with
    scenes = scenes_for(cfg)
    ckpt = RunCheckpoints(run_dir)
    best = best and ckpt.best.latest_step() is not None
    ckpt.check_scenes(scenes, scenes_name(cfg), best)      # before the model is built
    train = scenes.split_view("train")
    model = build_model(cfg, train)
    if cfg.savn:       # {"nav", "ll"}: the navigation model and SAVN's learned loss
        like = jax.eval_shape(lambda s: savn.init_meta(
            model, savn.build_learned_loss(), cfg, s, jax.random.PRNGKey(0)), train)
        if best:
            params, _ = ckpt.restore(like, best=True)
        else:
            runner_like = jax.eval_shape(lambda s: savn.init_savn_runner(
                cfg, model, savn.build_learned_loss(), make_optimizer(cfg), s,
                jax.random.PRNGKey(0)), train)
            version = _saved_version(run_dir)
            if version < savn.REFILL_VERSION:                   # its runner has no rows
                runner_like = runner_like.replace(rows=None)
            elif version < savn.LAYERED_VERSION:                # version 8's fast weights
                runner_like = runner_like.replace(rows=jax.eval_shape(
                    savn.legacy_rows, runner_like.rows))
            params = ckpt.restore(runner_like)[0].params
        return model, params, cfg
    like = init_params(model, jax.random.PRNGKey(0), train)
    if best:
        params, _ = ckpt.restore(like, best=True)
    else:
        runner_like = jax.eval_shape(lambda scenes: init_runner(   # shapes only: the
            cfg, model, make_optimizer(cfg), scenes, jax.random.PRNGKey(0)), train)  # train
                                                                    # rooms are not read
        runner, _ = ckpt.restore(runner_like)
        params = runner.params
    return model, params, cfg


def load_run_policy(run_dir: str | Path, best: bool = True, savn_act: str | None = None):
    """-> (Policy, params, config) of a training run (see load_run_model). savn_act
    ("greedy" | "sample") overrides a SAVN run's test-time actions (config.savn_act)."""
    model, params, cfg = load_run_model(run_dir, best)
    if savn_act is not None:
        if not cfg.savn:
            raise UserError(f"--savn-act: {run_dir} is a {cfg.model} run without SAVN: "
                            "expected a SAVN or D-SAVN run directory")
        if savn_act not in SAVN_ACTS:
            raise UserError(f"--savn-act {savn_act!r}: expected one of {list(SAVN_ACTS)}")
        cfg = dataclasses.replace(cfg, savn_act=savn_act)
    if cfg.savn:       # with SAVN's test-time inner steps (training/savn.py)
        return savn.run_policy(cfg, model, scenes_for(cfg)), params, cfg
    return model_policy(model, cfg.model), params, cfg
