"""TPN configuration: stage-2 training and the test-time update, one frozen dataclass.

    cfg = get_tpn_config(base_dir="runs/baseline-calibrated")     # defaults, run_dir base/tpn
    cfg = load_tpn_config("runs/baseline-calibrated/tpn")         # a stage-2 run's config
Every field is a command-line option (add_tpn_arguments: `--base DIR`, `--scope trunk`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path
from typing import Literal, get_args

from orgnav_jax.training.config_fields import (
    CONFIG_VERSION, COUNT, EPISODE_CAP, OLD_RENAMES, POSITIVE, READABLE_VERSIONS, RUN_RANGES,
    Range, add_field_options, budget_notice, check_ranges, check_types, given_options,
    host_only, run_fields,
)
from orgnav_jax.training.run_dir import read_config

Scope = Literal["actor", "trunk", "all"]     # parameters a test-time update changes
Detector = Literal["visited", "cosine"]      # external memory: visited set or feature match
When = Literal["deadlock", "all"]            # which steps update (Table 2: "all")
Target = Literal["tpn", "random"]            # update target (Table 2: "random")
Act = Literal["sample", "greedy"]            # the frozen base's actions in stage 2
# Where the TPN acts (docs/tpn_stage2.md): "state", ours: at a deadlock state, the
# policy's output there is corrected (CE with the TPN's prediction there) and the step is
# re-run with the new weights; stage 2 labels the deadlock state with its expert action.
# "release", the ECCV release's (agents/agent.py:149-205, runners/train_util.py:9-37):
# after step t, if s_{t+1} is a deadlock, CE(policy logits of step t, the TPN's prediction
# of step t), and the new weights act from step t+1 (step t is not re-run); stage 2
# labels the step that led into the deadlock with the expert action at s_{t+1}.
Placement = Literal["state", "release"]
StageOptim = Literal["ours", "release"]      # stage 2's optimiser (STAGE2_OPTIM)
SCOPES, DETECTORS, WHEN, TARGETS, ACTS, PLACEMENTS, STAGE_OPTIMS = (
    get_args(t) for t in (Scope, Detector, When, Target, Act, Placement, StageOptim))


# The test-time learning rate val chose for both bases (Baseline and ORG + IL; the
# sweeps and their val numbers: experiments/results/val_choices, docs/results.md).
TPN_LR = 1e-4          # the release's too (issue 41: chosen on val with the placement)


# The TPN's settings by concern. TPNConfig below is their one flat surface (config.json,
# command-line options); each consumer takes only its part: the network's widths
# (build_tpn), the deadlock detector (tpn/deadlock.py), the test-time update (the
# test-time policy's compile-cache key); stage 2's fields stay on TPNConfig.
@dataclasses.dataclass(frozen=True)
class TPNNetwork:
    """The TPN network's settings (models.tpn_net.TPN; its other widths follow the base's
    LSTM width, as the release's)."""
    action_embed: int = 6
    top_k: int = 10


@dataclasses.dataclass(frozen=True)
class DeadlockMemory:
    """The external memory that flags deadlock steps (tpn/deadlock.py)."""
    deadlock: Detector = "visited"
    cosine_threshold: float = 0.99
    signature_dim: int = 64


@dataclasses.dataclass(frozen=True)
class TestTime:
    """What the test-time policy reads: the update and its deadlock detector."""
    tpn_lr: float = TPN_LR
    scope: Scope = "all"
    when: When = "deadlock"
    target: Target = "tpn"
    reset_every: int = 50
    tpn_train_mode: bool = False
    placement: Placement = "release"
    deadlock: Detector = "visited"
    cosine_threshold: float = 0.99
    signature_dim: int = 64


@dataclasses.dataclass(frozen=True)
class TPNConfig(run_fields(updates_per_chunk=10, eval_every_chunks=5,
                           checkpoint_every_chunks=5, run_dir="")):
    # + the run's bookkeeping, declared in config_fields.run_fields (these defaults;
    # run_dir "": <base_dir>/tpn): updates_per_chunk, eval_every_chunks,
    # eval_episodes_per_room_type, checkpoint_every_chunks, keep_checkpoints, seed, run_dir
    # host_only: stage 2's programs do not read the base's directory, the budget or the
    # test-time update's fields (the test-time policy's key is TestTime)
    base_dir: str = host_only("", "tpn")   # the trained navigation run (best-on-val params)
    # the network (models.tpn_net.TPN; the release's head, other widths from the base's)
    action_embed: int = 6             # width of the embedded policy probabilities
    top_k: int = 10                   # memory slots read per step
    # the external memory (deadlock detection)
    deadlock: Detector = "visited"         # visited (revisited state or failed move) | cosine
    cosine_threshold: float = 0.99    # cosine: global feature match with an earlier step
    signature_dim: int = 64           # cosine: random projection width of the global map
    # stage 2: the frozen base acts in num_envs training episodes per update
    act: Act = "sample"               # sample | greedy (the base's actions in stage 2)
    episode_cap: int = 100            # stage-2 episode cap (test time: the eval caps)
    num_envs: int = 64
    optim: StageOptim = "release"     # the release's (STAGE2_OPTIM; chosen on val) | Adam (ours)
    lr: float = 3e-4
    max_grad_norm: float = 10.0
    total_episodes: int = host_only(40_000, "tpn")
    # test time (evaluation with --tpn)
    tpn_lr: float = host_only(TPN_LR, "tpn")   # one SGD step per update step (val chose)
    scope: Scope = host_only("all", "tpn")   # all (the release's) | trunk (above the
                                             # encoder) | actor
    when: When = host_only("deadlock", "tpn")
    target: Target = host_only("tpn", "tpn")
    reset_every: int = host_only(50, "tpn")   # fast weights back to the trained ones every
                                      # N steps of an episode (the release's 50); 0: at its
                                      # start only
    tpn_train_mode: bool = host_only(False, "tpn")   # the release's confound: dropout
                                                     # active with TPN
    placement: Placement = "release"  # where the TPN acts, both stages (Placement above;
                                      # chosen on val, issue 41)

    @property
    def num_updates(self) -> int:
        return max(1, self.total_episodes // self.num_envs)

    def budget_notice(self) -> str | None:
        """A one-line note when the episodes run differ from total_episodes, else None."""
        return budget_notice("total_episodes", self.total_episodes, self.num_envs,
                             self.updates_per_chunk, f"{self.num_envs} episodes")

    def validate(self) -> "TPNConfig":
        """Check every field's type and range; ValueError naming the field, its value and
        the expected range (FIELD_RANGES)."""
        check_types(self, "TPN config field")
        for name, allowed in (("scope", SCOPES), ("deadlock", DETECTORS), ("when", WHEN),
                              ("target", TARGETS), ("act", ACTS),
                              ("placement", PLACEMENTS), ("optim", STAGE_OPTIMS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"TPN config field {name!r}: {getattr(self, name)!r}, "
                                 f"expected one of {list(allowed)}")
        check_ranges(self, FIELD_RANGES, "TPN config field")
        if self.placement == "release" and self.deadlock != "visited":
            raise ValueError("TPN config field 'placement': 'release' goes with deadlock "
                             "'visited' (the release's revisit check after the move), got "
                             f"deadlock {self.deadlock!r}")
        return self

    @property
    def network(self) -> TPNNetwork:
        return _part(TPNNetwork, self)

    @property
    def memory(self) -> DeadlockMemory:
        return _part(DeadlockMemory, self)

    def test_time(self) -> TestTime:
        """The fields the test-time policy reads, so that runs which differ in
        directories, seeds or stage-2 budget share one compiled evaluation."""
        return _part(TestTime, self)

    def to_json(self) -> str:
        return json.dumps({"version": CONFIG_VERSION, "stage": "tpn",
                           **dataclasses.asdict(self)}, indent=1)



def _part(cls, cfg):
    return cls(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cls)})


FIELDS = {f.name for f in dataclasses.fields(TPNConfig)}

# The range of every numeric TPNConfig field.
FIELD_RANGES: dict[str, Range] = {
    **{f: COUNT for f in ("action_embed", "top_k", "signature_dim", "num_envs",
                          "total_episodes")},
    **RUN_RANGES,
    "episode_cap": EPISODE_CAP,
    "cosine_threshold": Range(lo=-1, hi=1),
    "lr": POSITIVE, "max_grad_norm": POSITIVE,
    "tpn_lr": Range(lo=0, note="0: no test-time update"),
    "reset_every": Range(lo=0, note="0: reset at episode starts only"),
}


# Stage 2's optimiser (`--optim`, TPNConfig.optim). "release": the release trains stage 2
# with its A3C optimiser (AMSGrad, eps 1e-3, lr 1e-4, gradient-norm clip 100 on the loss
# summed over an episode's steps) on training episodes capped at 30 steps; get_tpn_config
# fills these fields for it unless they are given.
STAGE2_OPTIM: dict[str, dict] = {
    "ours": {},
    "release": dict(lr=1e-4, max_grad_norm=100.0, episode_cap=30),
}
# Fields a version-6 (or older) TPN config lacks (config version 7, issue 41), with the
# values those runs used.
V7_DEFAULTS = {"placement": "state", "optim": "ours"}


def check_tpn_base(nav_cfg, base_dir) -> None:
    """A TPN's base must be a navigation run without SAVN: SAVN adapts by its own inner
    steps and its parameters hold the learned loss beside the network (docs/savn.md)."""
    if nav_cfg.savn:
        raise ValueError(f"--base {base_dir}: a SAVN run cannot be a TPN base (SAVN adapts "
                         "by its own inner steps; docs/savn.md): choose a run trained "
                         "without savn")


def get_tpn_config(**fields) -> TPNConfig:
    """Defaults with fields replaced; run_dir defaults to <base_dir>/tpn; the optimiser
    (optim, "release" by default) fills its STAGE2_OPTIM fields that are not given."""
    bad = sorted(set(fields) - FIELDS)
    if bad:
        raise ValueError(f"unknown TPN config field(s) {bad}; fields are {sorted(FIELDS)}")
    optim = fields.get("optim", TPNConfig.optim)     # the default optimiser's fields too
    cfg = TPNConfig(**{**STAGE2_OPTIM.get(optim, {}), **fields})
    if not cfg.run_dir and cfg.base_dir:
        cfg = dataclasses.replace(cfg, run_dir=str(Path(cfg.base_dir) / "tpn"))
    return cfg.validate()


# The fields of the TPN network before the release's head (issue 39): a config.json
# with one of them is a stage-2 run whose parameters this TPN cannot read.
OLD_HEAD_FIELDS = ("mlp",)


def load_tpn_config(run_dir: str | Path) -> TPNConfig:
    """The TPNConfig saved in a stage-2 run directory; clear errors otherwise (a run of the
    TPN head before issue 39 is refused: its parameters do not fit this network)."""
    path = Path(run_dir) / "config.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError):
        doc = None                        # read_config says what is wrong with it
    if isinstance(doc, dict) and doc.get("stage") == "tpn" and \
            any(f in doc for f in OLD_HEAD_FIELDS):
        raise ValueError(f"{path}: a stage-2 run of the TPN head before the release's "
                         "(issue 39; it has the field 'mlp'): its parameters do not fit "
                         "this TPN network; train stage 2 again (docs/tpn.md)")
    return read_config(run_dir, TPNConfig, "tpn", READABLE_VERSIONS,
                       {v: V7_DEFAULTS for v in READABLE_VERSIONS if v < 7}, OLD_RENAMES)


TEST_TIME_FIELDS = ("tpn_lr", "scope", "when", "target", "deadlock", "cosine_threshold",
                    "reset_every", "tpn_train_mode", "placement")


def add_tpn_arguments(ap: argparse.ArgumentParser, fields=None) -> None:
    """One --option per TPNConfig field (all, or those named in `fields`); base_dir is
    --base."""
    add_field_options(ap, TPNConfig, "TPN config fields", prefix="tpn__",
                      flags={"base_dir": "base"}, only=fields)


def tpn_overrides_from_args(args: argparse.Namespace) -> dict:
    return given_options(args, TPNConfig, prefix="tpn__")
