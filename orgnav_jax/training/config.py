"""Training configuration: one frozen dataclass, named presets, command-line overrides.

    cfg = get_config("small", num_envs=128)        # a preset with fields replaced
    cfg = config_from_args(["--preset", "small", "--lr", "3e-4"])
Every field is a command-line option (`--num-envs 128`, `--model org`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

CONFIG_VERSION = 3   # 2: the split LSTM trunk (new parameter layout); 3: il_norm, il_step
READABLE_VERSIONS = (2, 3)   # configs and checkpoints this version reads (same parameters)
# Fields a version-2 config lacks, with the values those runs were trained with.
V2_DEFAULTS = {"il_norm": "masked_mean", "il_step": "state"}

IL_MODES = ("none", "deadlock", "all", "failed")   # which steps get the imitation loss
IL_STEPS = ("cause", "state")        # supervise the action that led into a deadlock, or
                                     # the action taken at the deadlock state
IL_NORMS = ("per_step", "masked_mean")   # sum / (T*N) (as the release), or mean over IL steps


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    # data
    scene_preset: str = "small"       # scene preset built and cached (orgnav_jax.scenes)
    scenes_dir: str | None = None     # or a saved / imported SceneSet directory
    scene_seed: int = 0
    # model
    model: str = "baseline"           # baseline | we | org | org_released | dsp
    glob_channels: int = 16
    action_embed: int = 10
    fuse_channels: int = 16
    hidden: int = 128
    lstm_layers: int = 1
    dropout: float = 0.0              # on the global map's 1x1 layer (release: 0.25)
    # imitation (trial-driven IL): none | deadlock | all | failed (see IL_MODES, IL_STEPS)
    il: str = "none"
    il_weight: float = 1.0
    il_step: str = "state"
    il_norm: str = "per_step"
    # environment
    success_reward: float = 5.0
    step_penalty: float = -0.01
    max_steps: int = 30               # training episode cap
    # optimisation (synchronous A2C over num_envs environments)
    num_envs: int = 64
    rollout_len: int = 16
    lr: float = 7e-4
    adam_eps: float = 1e-5
    max_grad_norm: float = 10.0
    gamma: float = 0.99
    gae_lambda: float = 0.95
    entropy_coef: float = 0.01
    value_coef: float = 0.5
    total_env_steps: int = 3_000_000
    updates_per_chunk: int = 25       # jitted updates between host-side logging
    # evaluation and checkpoints
    eval_every_chunks: int = 8
    eval_episodes_per_room_type: int = 50   # val episodes during training (test: 250)
    checkpoint_every_chunks: int = 4
    keep_checkpoints: int = 2
    seed: int = 0
    run_dir: str = "runs/baseline-small"

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.rollout_len

    @property
    def num_updates(self) -> int:
        return max(1, self.total_env_steps // self.steps_per_update)

    def validate(self) -> "TrainConfig":
        from orgnav_jax.models import ENCODERS
        if self.model not in ENCODERS:
            raise ValueError(f"config field 'model': unknown model {self.model!r}, expected "
                             f"one of {sorted(ENCODERS)}")
        for name, allowed in (("il", IL_MODES), ("il_step", IL_STEPS),
                              ("il_norm", IL_NORMS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"config field {name!r}: {getattr(self, name)!r}, expected "
                                 f"one of {list(allowed)}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"config field 'dropout' must lie in [0, 1), got {self.dropout}")
        for f in ("num_envs", "rollout_len", "hidden", "lstm_layers", "updates_per_chunk",
                  "total_env_steps", "max_steps"):
            if getattr(self, f) < 1:
                raise ValueError(f"config field {f!r} must be >= 1, got {getattr(self, f)}")
        return self

    def to_json(self) -> str:
        return json.dumps({"version": CONFIG_VERSION, **dataclasses.asdict(self)}, indent=1)


PRESETS: dict[str, dict] = {
    # Small widths: learns on 2 CPU cores in minutes (the default run).
    "small": {},
    # The paper's widths (512x7x7 ResNet map, 512-d appearance, LSTM 512).
    # (The release's dropout 0.25 is not applied yet: see TrainConfig.validate.)
    "paper": dict(scene_preset="paper", glob_channels=64, fuse_channels=64, hidden=512,
                  lr=1e-4, run_dir="runs/baseline-paper"),
    # For tests: the tiny scene set, a short budget.
    "tiny": dict(scene_preset="tiny", total_env_steps=400_000, updates_per_chunk=10,
                 eval_every_chunks=8, run_dir="runs/tiny"),
}
# The rows of the paper's Tables 1 and 2, on the small benchmark (model x imitation).
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
}
# The rows use the release's dropout 0.25, which val preferred (docs/results.md); the
# default run ("small") keeps 0.
TABLE_DROPOUT = 0.25
PRESETS.update({name: dict(row, dropout=TABLE_DROPOUT, run_dir=f"runs/{name}-small")
                for name, row in TABLE_ROWS.items()})


def get_config(preset: str = "small", **overrides) -> TrainConfig:
    """A preset with fields replaced; clear errors for unknown presets or fields."""
    if preset not in PRESETS:
        raise ValueError(f"unknown training preset {preset!r}: expected one of "
                         f"{sorted(PRESETS)}")
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"unknown config field(s) {bad}; fields are {sorted(fields)}")
    return TrainConfig(**{**PRESETS[preset], **overrides}).validate()


STAGES = {"nav": "training", "tpn": "TPN (stage 2)"}


def read_config(run_dir: str | Path, cls, stage: str = "nav"):
    """config.json of a run directory -> cls(**fields).validate(), after checking its stage,
    version and field names; clear errors otherwise."""
    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: {run_dir} is not a {STAGES[stage]} run "
                                "directory")
    doc = json.loads(path.read_text())
    found = doc.pop("stage", "nav")
    if found != stage:
        raise ValueError(f"{path}: not a {STAGES[stage]} run, but a {STAGES.get(found, found)}"
                         " one")
    version = doc.pop("version", None)
    if version == 2 and cls is TrainConfig:
        doc = {**V2_DEFAULTS, **doc}
    if version not in READABLE_VERSIONS:
        raise ValueError(f"{path}: config version {version}, this orgnav_jax reads versions "
                         f"{list(READABLE_VERSIONS)}")
    bad = sorted(set(doc) - {f.name for f in dataclasses.fields(cls)})
    if bad:
        raise ValueError(f"{path}: unknown config field(s) {bad}")
    return cls(**doc).validate()


def load_config(run_dir: str | Path) -> TrainConfig:
    """The TrainConfig saved in a training run directory (see read_config)."""
    return read_config(run_dir, TrainConfig)


def _parse_bool(text: str) -> bool:
    if text.lower() in ("1", "true", "yes"):
        return True
    if text.lower() in ("0", "false", "no"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def add_config_arguments(ap: argparse.ArgumentParser) -> None:
    """One --option per TrainConfig field (default: the preset's value)."""
    group = ap.add_argument_group("config fields (override the preset)")
    for f in dataclasses.fields(TrainConfig):
        kind = {int: int, float: float, bool: _parse_bool}.get(
            type(f.default), str)
        group.add_argument("--" + f.name.replace("_", "-"), dest=f.name, type=kind,
                           default=None, metavar=type(f.default).__name__.upper()
                           if f.default is not None else "STR")


def overrides_from_args(args: argparse.Namespace) -> dict:
    names = {f.name for f in dataclasses.fields(TrainConfig)}
    return {k: v for k, v in vars(args).items() if k in names and v is not None}
