"""Training configuration: one frozen dataclass, named presets, command-line overrides.

    cfg = get_config("small", num_envs=128)        # a preset with fields replaced
Every field is a command-line option (`--num-envs 128`, `--model org`); a preset's runs
go to runs/<preset> (runs/<preset>-<scenes> on scenes not the preset's own; the default
preset's to runs/baseline-calibrated: default_run_dir) unless --run-dir says otherwise.
The machinery (version, ranges, checks, options) is shared with the TPN's config:
training/config_fields.py.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Literal, get_args

from orgnav_jax.constants import DEFAULT_SCENE_PRESET
from orgnav_jax.training.config_fields import (
    CONFIG_VERSION, COUNT, EPISODE_CAP, FINITE, NON_NEGATIVE, OLD_RENAMES, POSITIVE,
    READABLE_VERSIONS, RUN_RANGES, SEED, Range, add_field_options, budget_notice,
    check_ranges, check_types, given_options, host_only, run_fields,
)
from orgnav_jax.training.run_dir import read_config

# Fields a version-2 config lacks, with the values those runs were trained with.
V2_DEFAULTS = {"il_norm": "masked_mean", "il_step": "state"}
# Fields a version-3 (or 2) config lacks, with the values those runs were trained with
# (one device, float32): equal to the dataclass defaults, kept here as the record.
V3_DEFAULTS = {"devices": 0, "dtype": "float32"}
# Fields a version-5 (or older) config lacks: those runs are not SAVN runs (issue 25).
V5_DEFAULTS = {"savn": False, "savn_steps": 6, "savn_inner_lr": 1e-4,
               "savn_inner_steps": 4, "savn_first_order": False}
# Fields a version-6 (or older) config lacks: those runs were trained with the networks
# before parity with the release (issue 39): they keep them, and evaluate as trained.
V6_DEFAULTS = {"net": "pre_parity", "prev_action": "onehot"}
# Fields a version-6 (or older) config lacks, added with config version 7 (issues 40 and
# 41), with the values those runs were trained with: WE's one-hot target maps, this
# project's optimiser, greedy SAVN evaluation. (The brief of issues 40/41 called this dict
# V7_DEFAULTS, counting issue 39 as version 7; issue 39 kept version 6, so the runs these
# values describe are version 6 and older.)
V7_DEFAULTS = {"target_input": "onehot_maps", "word_vectors": None, "optim": "ours",
               "savn_act": "greedy"}
# Fields a version-7 (or older) config lacks, added with config version 8 (issue 40's
# refill of SAVN's batch rows). Those runs' SAVN updates stepped num_envs whole episodes to
# the cap (5 segments of 6 steps at the defaults) and their checkpoints hold no running
# episodes: they evaluate as trained, a resume is refused (training/loop.py).
V8_DEFAULTS = {"savn_segments": 5}
# Values whose meaning changed with config version 7 (issue 40), old -> the value that
# means it now, for the configs of version 6 and older: "dsp" was the D-SP whose graph
# replaces the detection maps (models/org.py), now "dsp_replace".
V6_VALUES = {"model": {"dsp": "dsp_replace"}}

# String modes are Literal types; their values (typing.get_args) are what validate
# accepts, and every dispatch on them is a dict that raises on other values
# (errors.choose).
ILMode = Literal["none", "deadlock", "all", "failed"]   # which steps get the imitation loss
ILStep = Literal["cause", "state"]   # supervise the action that led into a deadlock, or
                                     # the action taken at the deadlock state
ILNorm = Literal["per_step", "masked_mean"]   # sum / (T*N) (as the release), or mean over
                                              # the IL steps
Net = Literal["release", "pre_parity"]   # the networks as the release computes them, or as
                                         # this project did before issue 39 (docs/training.md)
PrevAction = Literal["probs", "onehot"]  # previous step's action probabilities (release), or
                                         # a one-hot of the action taken
TargetInput = Literal["word_vector", "onehot_maps"]   # WE / SAVN's target: SAVN's word
                                         # vector -> 64 tiled channels, or (before issue
                                         # 41) a one-hot -> 22 learned 7x7 maps
Optim = Literal["ours", "release"]       # the optimiser and advantage settings (OPTIM)
SavnAct = Literal["greedy", "sample"]    # SAVN's test-time actions (the release samples)
VTNetMask = Literal["none", "undetected"]   # VTNet's attention masks: none (the release)
                                         # or undetected categories (but the target)
                                         # dropped from the keys
DType = Literal["float32", "bfloat16"]   # the compute dtype of matmuls and activations
                                       # (parameters and optimizer state stay float32)
IL_MODES, IL_STEPS, IL_NORMS = get_args(ILMode), get_args(ILStep), get_args(ILNorm)
NETS, PREV_ACTIONS = get_args(Net), get_args(PrevAction)
TARGET_INPUTS, OPTIMS, SAVN_ACTS = get_args(TargetInput), get_args(Optim), get_args(SavnAct)
VTNET_MASKS = get_args(VTNetMask)
DTYPES = get_args(DType)


@dataclasses.dataclass(frozen=True)
class TrainConfig(run_fields(updates_per_chunk=25, eval_every_chunks=8,
                             checkpoint_every_chunks=4,
                             run_dir=f"runs/baseline-{DEFAULT_SCENE_PRESET}")):
    # + the run's bookkeeping, declared in config_fields.run_fields (these defaults; a
    # preset's run_dir: default_run_dir): updates_per_chunk, eval_every_chunks,
    # eval_episodes_per_room_type, checkpoint_every_chunks, keep_checkpoints, seed, run_dir
    # data. Host-only (host_only: no jitted program reads them; they only say where the
    # rooms come from: the rooms are the programs' input, their shapes key jit's own
    # cache, and their feature widths are in the model)
    scene_preset: str = host_only(DEFAULT_SCENE_PRESET)   # scene preset built and cached
                                                          # (orgnav_jax.scenes)
    scenes_dir: str | None = host_only(None)   # or a saved / imported SceneSet directory
    scene_seed: int = host_only(0)
    # model
    model: str = "baseline"           # baseline | we | org | org_released | dsp | dsp_replace
    glob_channels: int = 16
    action_embed: int = 10
    fuse_channels: int = 16
    hidden: int = 128
    lstm_layers: int = 2              # the release's nn.LSTM(3136, 512, 2)
    dropout: float = 0.0              # element-wise, after the global map's 1x1 layer and
                                      # the fusion 1x1 layer (release: 0.25 at both)
    net: Net = "release"              # trunk, released ORG wiring and init (docs/training.md)
    prev_action: PrevAction = "probs"
    # WE / SAVN's target input (model "we"; models/encoders.py, docs/savn.md)
    target_input: TargetInput = "word_vector"
    word_vectors: str | None = None   # a GloVe text file; None: the stand-in (seeded
                                      # random unit vectors, models/word_vectors.py)
    word_vectors_sha256: str | None = None   # sha256 of the (22, D) vectors read from
                                      # word_vectors, set when a run starts (given: the
                                      # vectors must be these); evaluation and resume
                                      # refuse other vectors (training/runs.py)
    # VTNet (model "vtnet": models/vtnet.py, docs/vtnet.md; issue 43). The transformer's
    # width (the release's d_model, 256 at paper widths), heads, FFN width and layers; the
    # per-cell width is fuse_channels and the LSTM width hidden. Fields added within config
    # version 8: their defaults are what every earlier run was (no VTNet).
    vtnet_dim: int = 16               # small widths (docs/vtnet.md: chosen for the speed
    vtnet_heads: int = 1              # target, 1/3 of the Baseline's env-steps/s on 2
    vtnet_ffn: int = 32               # cores: 16 ~0.5, 24 ~0.27-0.40, 32 ~0.27-0.30)
    vtnet_encoder_layers: int = 1
    vtnet_decoder_layers: int = 1
    vtnet_mask: VTNetMask = "none"
    # VTNet's pre-training (--stage pretrain: training/pretrain.py): the visual transformer
    # and a linear head learn the expert's action at random (state, target) pairs of the
    # training rooms; AdamW, gradient-norm clip, the lr x0.1 every pretrain_lr_drop
    # samples (0: never). pretrained: a pre-training run whose best-on-val visual
    # parameters start this run's, trained at pretrained_lr_scale x lr (the release's
    # pretrained_lr 1e-5 against lr 1e-4). The pre-training's own fields are host-only
    # in stage 1 ("nav"), its budgets in both stages
    pretrain_samples: int = host_only(4_000_000)   # chosen on val (seed 100; docs/vtnet.md)
    pretrain_batch: int = host_only(128, "nav")
    pretrain_lr: float = host_only(1e-4, "nav")
    pretrain_weight_decay: float = host_only(1e-4, "nav")
    pretrain_lr_drop: int = host_only(0, "nav")
    pretrain_clip: float = host_only(0.1, "nav")
    pretrain_val_samples: int = host_only(4096)
    pretrained: str | None = host_only(None, "pretrain")   # stage 1 reads whether there is
                                      # one, not where (training/loop.py: compute_config)
    pretrained_lr_scale: float = 0.1
    # imitation (trial-driven IL): none | deadlock | all | failed (see IL_MODES, IL_STEPS)
    il: ILMode = "none"
    il_weight: float = 0.3            # step, norm and weight chosen on val (issue 42;
    il_step: ILStep = "cause"         #   experiments/results/val_choices, docs/training.md)
    il_norm: ILNorm = "per_step"
    # environment
    success_reward: float = 5.0
    step_penalty: float = -0.01
    episode_cap: int = 30             # training episodes end after this many steps
    # optimisation (synchronous A2C over num_envs environments). optim "release":
    # AMSGrad and the loss summed over the rollout's steps (an episode's sum, as the
    # release); get_config then also sets OPTIM["release"]'s fields (docs/training.md)
    optim: Optim = "ours"
    num_envs: int = 64
    rollout_len: int = 16
    lr: float = 7e-4
    adam_eps: float = 1e-5
    max_grad_norm: float = 10.0
    gamma: float = 0.99
    gae_lambda: float = 0.95
    entropy_coef: float = 0.01
    value_coef: float = 0.5
    total_env_steps: int = host_only(3_000_000)   # the budget: the host counts it
    # scale-out (docs/scale_out.md)
    devices: int = host_only(0)       # devices per process the env axis is sharded over
                                      # (0: all local devices); a resume may change it.
                                      # Host-only: the mesh is a key of its own
    dtype: DType = "float32"          # bfloat16: bf16 matmuls, float32 parameters
    # SAVN (training/savn.py, docs/savn.md): episodes cut into segments of savn_steps
    # steps; after each of the first savn_inner_steps segments that did not end the
    # episode, one SGD step (savn_inner_lr) on the learned loss; MAML meta-gradient (first
    # order: the inner gradient is a constant). An update steps every batch row for
    # savn_segments segments; a row whose episode ended starts a new one at the next
    # segment boundary, a running episode goes on in the next update
    savn: bool = False
    savn_steps: int = 6               # k, the release's num_steps
    savn_segments: int = 5            # segments per update (num_envs x 5 x k env steps)
    savn_inner_lr: float = 1e-4       # the release's inner_lr
    savn_inner_steps: int = 4         # inner steps per episode (the release's gradient_limit)
    savn_first_order: bool = False
    savn_act: SavnAct = "sample"      # test-time actions: sampled (the release), or greedy

    @property
    def steps_per_update(self) -> int:
        """Env steps an update counts for the budget. SAVN: the most an update can take
        (num_envs rows x savn_segments x savn_steps); its budget counts the steps the
        episodes really took (training/loop.py: nav_stage, issue 40)."""
        if self.savn:
            return self.num_envs * self.savn_segments * self.savn_steps
        return self.num_envs * self.rollout_len

    @property
    def num_updates(self) -> int:
        return max(1, self.total_env_steps // self.steps_per_update)

    def budget_notice(self) -> str | None:
        """A one-line note when the env steps run differ from total_env_steps, else None
        (SAVN: None; it runs to the first chunk whose real env steps reach the budget)."""
        if self.savn:
            return None
        return budget_notice("total_env_steps", self.total_env_steps, self.steps_per_update,
                             self.updates_per_chunk, f"{self.num_envs} envs x "
                                                     f"{self.rollout_len} steps")

    def validate(self) -> "TrainConfig":
        """Check every field's type and range; ValueError naming the field, its value and
        the expected range (FIELD_RANGES, docs/training.md)."""
        # the models (jax: seconds) on first use: configs are read where jax is not
        # (api, the command lines' --help); ENCODERS is the one list of model names
        from orgnav_jax.models import ENCODERS
        check_types(self, "config field")
        if self.model not in ENCODERS:
            raise ValueError(f"config field 'model': unknown model {self.model!r}, expected "
                             f"one of {sorted(ENCODERS)}")
        for name, allowed in (("il", IL_MODES), ("il_step", IL_STEPS),
                              ("il_norm", IL_NORMS), ("dtype", DTYPES), ("net", NETS),
                              ("prev_action", PREV_ACTIONS),
                              ("target_input", TARGET_INPUTS), ("optim", OPTIMS),
                              ("savn_act", SAVN_ACTS), ("vtnet_mask", VTNET_MASKS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"config field {name!r}: {getattr(self, name)!r}, expected "
                                 f"one of {list(allowed)}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"config field 'dropout' must lie in [0, 1), got {self.dropout}")
        check_ranges(self, FIELD_RANGES, "config field")
        check_word_vectors_fields(self)
        check_vtnet(self)
        if self.savn:
            for name, ok, want in (("il", self.il == "none", "'none' with savn"),
                                   ("dropout", self.dropout == 0.0, "0 with savn"),
                                   ("dtype", self.dtype == "float32", "'float32' with savn")):
                if not ok:
                    raise ValueError(f"config field {name!r}: {getattr(self, name)!r}, "
                                     f"expected {want} (docs/savn.md)")
            check_savn_segments(self)
        return self

    def to_json(self) -> str:
        return json.dumps({"version": CONFIG_VERSION, **dataclasses.asdict(self)}, indent=1)


# The range of every numeric TrainConfig field (dropout: [0, 1), checked apart).
FIELD_RANGES: dict[str, Range] = {
    **RUN_RANGES, "scene_seed": SEED,
    "devices": Range(lo=0, note="0: all local devices"),
    **{f: COUNT for f in ("glob_channels", "action_embed", "fuse_channels", "hidden",
                          "lstm_layers", "num_envs", "rollout_len", "total_env_steps",
                          "savn_steps", "savn_inner_steps", "savn_segments")},
    # the env counts steps in int32 and keeps a trail of episode_cap + 1 states per env
    # (the memory check, training/memory.py, bounds it far lower)
    "episode_cap": EPISODE_CAP,
    "lr": POSITIVE, "adam_eps": POSITIVE, "max_grad_norm": POSITIVE,
    "gamma": Range(lo=0, hi=1, lo_open=True),
    "gae_lambda": Range(lo=0, hi=1),
    "entropy_coef": NON_NEGATIVE, "value_coef": NON_NEGATIVE, "il_weight": NON_NEGATIVE,
    "success_reward": FINITE, "step_penalty": FINITE,
    "savn_inner_lr": Range(lo=0, note="0: no inner update"),
    **{f: COUNT for f in ("vtnet_dim", "vtnet_heads", "vtnet_ffn", "vtnet_encoder_layers",
                          "vtnet_decoder_layers", "pretrain_samples", "pretrain_batch",
                          "pretrain_val_samples")},
    "pretrain_lr": POSITIVE, "pretrain_clip": POSITIVE,
    "pretrain_weight_decay": NON_NEGATIVE, "pretrained_lr_scale": NON_NEGATIVE,
    "pretrain_lr_drop": Range(lo=0, note="0: no drop"),
}


def check_word_vectors_fields(cfg: TrainConfig) -> None:
    """word_vectors only where a model reads them (WE / SAVN's target: model 'we' with
    target_input 'word_vector'), as a non-empty path; word_vectors_sha256 only with it,
    as 64 hex digits. ValueError naming the field (a file given to a model that reads
    none was kept in the config and silently ignored)."""
    reads = cfg.model == "we" and cfg.target_input == "word_vector"
    if cfg.word_vectors is not None and (not reads or not cfg.word_vectors.strip()):
        why = (f"model {cfg.model!r} reads no word vectors" if cfg.model != "we" else
               f"target_input {cfg.target_input!r} reads no word vectors" if not reads
               else "an empty path")
        raise ValueError(f"config field 'word_vectors': {cfg.word_vectors!r}, expected a "
                         "GloVe text file, with model 'we' and target_input 'word_vector' "
                         f"(WE, SAVN): {why}")
    digest = cfg.word_vectors_sha256
    if digest is not None and (cfg.word_vectors is None or len(digest) != 64 or
                               any(c not in "0123456789abcdef" for c in digest)):
        raise ValueError(f"config field 'word_vectors_sha256': {digest!r}, expected 64 "
                         "lower-case hex digits, with word_vectors (the sha256 of its "
                         "vectors)")


def check_savn_segments(cfg: TrainConfig) -> None:
    """SAVN's fields against the episode cap: a segment must end before the cap for an
    inner step to happen during training (training/savn.py, savn_loss: `hi < cap`), so
    savn_steps >= episode_cap would train with no inner step at all; ValueError naming
    the field otherwise. (More savn_inner_steps than training episodes can hold are
    allowed: the evaluation's longer caps use them; the memory check bounds their slots,
    training/memory.py.)"""
    if cfg.savn_steps >= cfg.episode_cap:
        raise ValueError(f"config field 'savn_steps': {cfg.savn_steps}, expected < "
                         f"episode_cap {cfg.episode_cap} with savn: segments of "
                         f"{cfg.savn_steps} steps leave no inner step in a "
                         f"{cfg.episode_cap}-step training episode (docs/savn.md)")


def check_vtnet(cfg: TrainConfig) -> None:
    """VTNet's fields that go together (ValueError naming the field): the width splits
    into the heads and into the two halves of the position embedding and is wider than
    the 7 location features; the release's networks; `pretrained` only with VTNet."""
    if cfg.pretrained is not None and (cfg.model != "vtnet" or not cfg.pretrained.strip()):
        raise ValueError(f"config field 'pretrained': {cfg.pretrained!r}, expected a "
                         "pre-training run directory, with model 'vtnet'")
    if cfg.model != "vtnet":
        return
    for name, ok, want in (
            ("vtnet_dim", cfg.vtnet_dim % 4 == 0 and cfg.vtnet_dim > 7,
             "a multiple of 4 above 7 (two sine halves; 7 location features)"),
            ("vtnet_heads", cfg.vtnet_dim % cfg.vtnet_heads == 0,
             f"a divisor of vtnet_dim {cfg.vtnet_dim}"),
            ("net", cfg.net == "release", "'release' with model vtnet")):
        if not ok:
            raise ValueError(f"config field {name!r}: {getattr(cfg, name)!r}, expected {want}")


# VTNet's transformer at paper widths: the release's defaults (d_model 256, 8 heads, FFN
# 512, 6 encoder and 6 decoder layers: models/vtnetmodel.py, utils/command_parser.py)
VTNET_PAPER = dict(vtnet_dim=256, vtnet_heads=8, vtnet_ffn=512, vtnet_encoder_layers=6,
                   vtnet_decoder_layers=6)
TRAIN_PRESETS: dict[str, dict] = {
    # Small widths: learns on 2 CPU cores in minutes (the default run).
    "small": {},
    # The paper's widths (512x7x7 ResNet map, 512-d appearance, LSTM 512).
    "paper": dict(scene_preset="paper", glob_channels=64, fuse_channels=64, hidden=512,
                  **VTNET_PAPER,
                  lr=1e-4, run_dir="runs/paper"),
    # For tests: the tiny scene set, a short budget.
    "tiny": dict(scene_preset="tiny", total_env_steps=400_000, updates_per_chunk=10,
                 eval_every_chunks=8, run_dir="runs/tiny"),
}
# The rows of the paper's Tables 1 and 2 (model x imitation), on the default scene preset.
# Both SAVN rows: one LSTM layer as SAVN's release, inner lr 1e-3 chosen on val at 5 M
# real steps (the release's 1e-4 stays the field's default;
# experiments/results/val_choices/savn.md, docs/savn.md)
SAVN_ROW = dict(savn=True, lstm_layers=1, savn_inner_lr=1e-3)
TABLE_ROWS: dict[str, dict] = {
    "baseline": dict(model="baseline", il="none"),
    "we": dict(model="we", il="none"),
    "il": dict(model="baseline", il="deadlock"),          # Baseline + IL
    "il_all": dict(model="baseline", il="all"),           # IL on every step (Table 2)
    "il_failed": dict(model="baseline", il="failed"),     # IL on failed moves only
    "org": dict(model="org", il="none"),                  # Baseline + ORG
    "org_il": dict(model="org", il="deadlock"),           # ORG + IL
    "org_released": dict(model="org_released", il="none"),
    "dsp": dict(model="dsp", il="none"),                  # D-SP (prior knowledge graph)
    # SAVN's release has one LSTM layer (an LSTMCell: allenai/savn models/basemodel.py)
    "savn": dict(model="we", il="none", **SAVN_ROW),        # SAVN (word embedding)
    "dsavn": dict(model="baseline", il="none", **SAVN_ROW),  # D-SAVN
}
# The rows' dropout: val chose 0 over the release's 0.25 (Baseline, seed 100, 2 M env
# steps: 69.0 vs 65.5 val success; experiments/results/val_choices, docs/results.md).
TABLE_DROPOUT = 0.0
TRAIN_PRESETS.update({name: dict(row, dropout=TABLE_DROPOUT, run_dir=f"runs/{name}")
                for name, row in TABLE_ROWS.items()})
# VTNet (issue 43; docs/vtnet.md), with the rows' settings: the
# release trains it by A3C alone (no IL). `--preset vtnet` pre-trains it first (a run in
# RUN_DIR-pretrain: train.py), then trains from it; vtnet_scratch has no pre-training.
# (Not TABLE_ROWS: experiments/run_table.py adds them as rows, `vtnet` with its
# pre-training per seed before A2C.)
VTNET_PRESETS = {"vtnet": dict(model="vtnet", il="none"),
                 "vtnet_scratch": dict(model="vtnet", il="none")}
TRAIN_PRESETS.update({name: dict(row, dropout=TABLE_DROPOUT, run_dir=f"runs/{name}")
                      for name, row in VTNET_PRESETS.items()})


# The optimiser and advantage settings (`--optim`, docs/training.md). "release": the ECCV
# release's (utils/command_parser.py, main.py, optimizers/shared_adam.py,
# runners/a3c_train.py): lr 1e-4, Adam eps 1e-3 with AMSGrad, gradient-norm clip 100 on
# the loss summed over steps, GAE tau 1 (Monte-Carlo value targets), rollouts of a whole
# capped episode's length (30 steps); SAVN rows: no clipping (allenai/savn). get_config
# fills these fields for optim "release" unless they are given.
OPTIM: dict[str, dict] = {
    "ours": {},
    "release": dict(lr=1e-4, adam_eps=1e-3, max_grad_norm=100.0, gae_lambda=1.0,
                    rollout_len=30),
}


@dataclasses.dataclass(frozen=True)
class Budget:
    """A named training budget (--budget): stage-1 env steps and stage-2 episodes.

    Stage 1 counts env steps (whole updates of num_envs x rollout_len steps with
    auto-reset), not episodes: an episode budget E becomes E x steps_per_episode env
    steps, with steps_per_episode the mean training episode length (the cap is 30)."""
    episodes: int              # stage-1 episodes the budget stands for
    steps_per_episode: int     # mean env steps per training episode assumed
    tpn_episodes: int          # stage-2 (TPN) training episodes
    source: str                # where steps_per_episode comes from

    @property
    def env_steps(self) -> int:
        return self.episodes * self.steps_per_episode

    def describe(self) -> str:
        return (f"budget: {self.episodes:,} episodes x {self.steps_per_episode} env steps "
                f"per episode ({self.source}) = {self.env_steps:,} env steps for stage 1; "
                f"{self.tpn_episodes:,} episodes for the TPN")


BUDGETS: dict[str, Budget] = {
    # The paper: 6 M training episodes (12 A3C workers), then 2 M episodes for the TPN.
    # Episode length: env steps per finished episode over whole 5 M-step runs of the small
    # benchmark's table made before parity (experiments/results/before_parity/table_5m, 14
    # runs of baseline / IL / ORG / ORG+IL / IL-all / IL-failed, 3 seeds): 15.3-16.7, mean
    # 16.2 (early episodes are short: the untrained policy says Done at random; the
    # 30-step cap bounds it).
    "paper": Budget(episodes=6_000_000, steps_per_episode=16, tpn_episodes=2_000_000,
                    source="the mean training episode length of 5 M-step runs on the "
                           "small benchmark, 15.3-16.7; the 30-step cap would give 180 M"),
}


def default_run_dir(preset: str, overrides: dict | None = None) -> str:
    """Where a run of `preset` goes when no run_dir is given, named after what it is:
    runs/<preset>, with -<scenes> where its scenes (the scene preset, or the scenes_dir
    folder's name, in `overrides`) are not the preset's own (runs/we-small); the default
    preset `small` (the Baseline at small widths; its name is also a scene preset's) names
    its scenes always: runs/baseline-calibrated."""
    overrides = overrides or {}
    row = TRAIN_PRESETS.get(preset, {})
    own = row.get("scene_preset", DEFAULT_SCENE_PRESET)
    scenes = (Path(overrides["scenes_dir"]).name if overrides.get("scenes_dir")
              else overrides.get("scene_preset", own))
    if preset == "small":
        return f"runs/baseline-{scenes}"
    base = row.get("run_dir", f"runs/{preset}")
    return base if scenes == own and not overrides.get("scenes_dir") else f"{base}-{scenes}"


def get_config(preset: str = "small", **overrides) -> TrainConfig:
    """A preset with fields replaced; clear errors for unknown presets or fields. Without
    a run_dir, the run goes to default_run_dir(preset, overrides)."""
    if preset not in TRAIN_PRESETS:
        raise ValueError(f"unknown training preset {preset!r}: expected one of "
                         f"{sorted(TRAIN_PRESETS)}")
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"unknown config field(s) {bad}; fields are {sorted(fields)}")
    fields = {**TRAIN_PRESETS[preset], **overrides}
    run_dir = {} if "run_dir" in overrides else {"run_dir": default_run_dir(preset, overrides)}
    return TrainConfig(**{**TRAIN_PRESETS[preset], **OPTIM.get(fields.get("optim"), {}),
                          **run_dir, **overrides}).validate()


def load_config(run_dir: str | Path) -> TrainConfig:
    """The TrainConfig saved in a training run directory (run_dir.read_config)."""
    return read_config(run_dir, TrainConfig, "nav", READABLE_VERSIONS,
                       {2: {**V2_DEFAULTS, **V3_DEFAULTS, **V5_DEFAULTS, **V6_DEFAULTS,
                            **V7_DEFAULTS, **V8_DEFAULTS},
                        3: {**V3_DEFAULTS, **V5_DEFAULTS, **V6_DEFAULTS, **V7_DEFAULTS,
                            **V8_DEFAULTS},
                        4: {**V5_DEFAULTS, **V6_DEFAULTS, **V7_DEFAULTS, **V8_DEFAULTS},
                        5: {**V5_DEFAULTS, **V6_DEFAULTS, **V7_DEFAULTS, **V8_DEFAULTS},
                        6: {**V6_DEFAULTS, **V7_DEFAULTS, **V8_DEFAULTS},
                        7: V8_DEFAULTS},
                       OLD_RENAMES, {v: V6_VALUES for v in (2, 3, 4, 5, 6)},
                       required={"scene_preset": SCENE_PRESET_MISSING})


# Why a run's config must name its scene preset: the default changed from `small` to
# `calibrated` (2026-12-05, commit ddb4013) within config version 9, so a config without
# one (every config this program writes has it) cannot say which the run was trained on.
SCENE_PRESET_MISSING = (
    "expected the scene preset the run was trained on (this program writes it in every "
    "run's config; the default was 'small' before 2026-12-05 and is 'calibrated' since): "
    'add it, e.g. "scene_preset": "small"')


PRETRAIN_STAGE = "pretrain"      # a pre-training run's config.json (run_dir.STAGES)


@dataclasses.dataclass(frozen=True)
class PretrainConfig(TrainConfig):
    """A pre-training run's config: the TrainConfig of the VTNet it pre-trains (model
    widths, scenes, seed, dtype, the pretrain_* fields), saved with stage "pretrain"."""

    @classmethod
    def of(cls, cfg: TrainConfig, **changes) -> "PretrainConfig":
        return cls(**{**dataclasses.asdict(cfg), **changes}).validate()

    def validate(self) -> "PretrainConfig":
        super().validate()
        if self.model != "vtnet":
            raise ValueError(f"config field 'model': {self.model!r}, expected 'vtnet' "
                             "(pre-training trains VTNet's visual transformer)")
        if self.pretrained is not None:
            raise ValueError(f"config field 'pretrained': {self.pretrained!r}, expected "
                             "null in a pre-training run (it starts from the release's "
                             "initialisation)")
        return self

    @property
    def num_updates(self) -> int:
        return max(1, self.pretrain_samples // self.pretrain_batch)

    @property
    def total_samples(self) -> int:
        """The samples the budget trains: whole batches (pretrain_samples rounded down)."""
        return self.num_updates * self.pretrain_batch

    def budget_notice(self) -> str | None:
        return budget_notice("pretrain_samples", self.pretrain_samples, self.pretrain_batch,
                             self.updates_per_chunk, f"batches of {self.pretrain_batch}")

    def to_json(self) -> str:
        return json.dumps({"version": CONFIG_VERSION, "stage": PRETRAIN_STAGE,
                           **dataclasses.asdict(self)}, indent=1)


def load_pretrain_config(run_dir: str | Path) -> PretrainConfig:
    """The PretrainConfig saved in a pre-training run directory (one-line errors)."""
    return read_config(run_dir, PretrainConfig, PRETRAIN_STAGE, READABLE_VERSIONS,
                       required={"scene_preset": SCENE_PRESET_MISSING})


def add_config_arguments(ap: argparse.ArgumentParser) -> None:
    """One --option per TrainConfig field (default: the preset's value)."""
    add_field_options(ap, TrainConfig, "config fields (override the preset)")


def overrides_from_args(args: argparse.Namespace) -> dict:
    return given_options(args, TrainConfig)
