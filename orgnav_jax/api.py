"""The library API: what the command lines, experiments and notebooks call.

    from orgnav_jax import api
    result = api.evaluate_policy("expert", split="val", scene_preset="tiny")
    summary = api.train(get_config("baseline"))               # stage 1
    summary = api.train_tpn(get_tpn_config(base_dir=RUN))      # stage 2
    summary = api.pretrain(PretrainConfig.of(get_config("vtnet"), run_dir=PRE))   # VTNet
    result = api.evaluate_run(RUN, split="test")               # stage-1 or TPN run
    summary = api.train_both(get_config("org_il"), tpn_lr=1e-3)
    summaries = api.train_seeds(get_config("baseline"), seeds=(0, 1, 2))   # one program

Every function returns its results and raises on bad input (UserError, ValueError,
OSError, with messages naming the file or field); none prints results or exits. The
CLIs (`python -m orgnav_jax.train`, `python -m orgnav_jax.evaluate`) turn the errors
into one-line messages with exit code 2 (errors.run_cli).

Imports: the jax-based layers (evaluation, the trainers, the models, the scene sets) are
imported inside the functions that use them, marked "jax-based: on first use", so that
`import orgnav_jax.api` stays light (no jax: a fraction of a second, not seconds) for
what needs none of them: the command lines' --help and argument errors, and the tables
and checks that read run directories only.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

from orgnav_jax.constants import (
    DEFAULT_SCENE_PRESET, EPISODES_PER_ROOM_TYPE, IMAGE_SIZE, ROOM_TYPES)
from orgnav_jax.errors import UserError
from orgnav_jax.safe_write import check_output_file, json_text, write_text_atomic
from orgnav_jax.tables.convergence import check_stop_rule, stop_when_converged
from orgnav_jax.tpn.config import TEST_TIME_FIELDS, get_tpn_config
from orgnav_jax.training.config import PretrainConfig, TrainConfig, load_config
from orgnav_jax.training.run_dir import is_run_dir, seed_run_dir

RESULTS = "an evaluation results JSON of orgnav_jax.evaluate"
# host memory one evaluated episode takes at its peak (sampling ~90 B, measured with
# tracemalloc; per-episode arrays and the results' per-episode lists and text): an
# over-estimate, for refusing episode counts that cannot fit before sampling them
EPISODE_BYTES = 500
EPISODE_FILE = "an episode file of orgnav_jax.evaluate"


@dataclasses.dataclass
class LoadedPolicy:
    """A policy with its parameters and the scenes it belongs to."""
    policy: object               # evaluation.Policy
    params: object               # its parameters (None for random / expert)
    name: str                    # for file names and tables
    scene_preset: str = DEFAULT_SCENE_PRESET
    scenes_dir: str | None = None
    scene_seed: int = 0
    batch_size: int = 1000       # episodes per jitted batch
    from_run: bool = False       # a run's policy (its scenes are the run's own)


def load_policy(policy: str | None = None, run_dir: str | None = None,
                tpn_dir: str | None = None, release_checkpoint: str | None = None,
                release_kind: str = "GraphModel", savn_act: str | None = None,
                **test_time) -> LoadedPolicy:
    """One of: a named policy ('random', 'expert'), a training run's best-on-val model
    (run_dir), a stage-2 run (tpn_dir: its base with TPN's test-time updates;
    test_time overrides tpn.config.TEST_TIME_FIELDS), or a checkpoint of the authors'
    release (release_checkpoint, of release_kind: models/release.py; greedy, on the
    scenes the caller names, whose feature widths must be the checkpoint's; a
    MetaMemoryGraphModel with the test-time updates of its TPN head, test_time
    overriding the release's settings, tpn_lr 0 for none). savn_act
    ("greedy" | "sample") overrides a SAVN run's test-time actions."""
    from orgnav_jax import evaluation  # jax-based: on first use
    from orgnav_jax.models import release  # jax-based: on first use
    from orgnav_jax.tpn.test_time import (  # jax-based: on first use
        default_batch_size, load_tpn_policy, tpn_name, tpn_policy)
    # jax-based: on first use
    from orgnav_jax.training.runs import load_run_policy, model_policy
    if sum(x is not None for x in (policy, run_dir, tpn_dir, release_checkpoint)) > 1:
        raise UserError("give one of a policy name, a run directory, a TPN run directory or "
                        "a release checkpoint")
    release_tpn = release_checkpoint is not None and release_kind == "MetaMemoryGraphModel"
    if test_time and tpn_dir is None and not release_tpn:
        options = ", ".join("--" + f.replace("_", "-") for f in TEST_TIME_FIELDS)
        raise UserError(f"test-time TPN options ({options}) need --tpn TPN_RUN_DIR or "
                        "--release-kind MetaMemoryGraphModel")
    if savn_act is not None and run_dir is None:
        raise UserError("--savn-act needs --checkpoint RUN_DIR of a SAVN or D-SAVN run")
    if tpn_dir is not None:
        pol, params, run_cfg, tpn_cfg = load_tpn_policy(tpn_dir, **test_time)
        return LoadedPolicy(pol, params, f"{Path(tpn_cfg.base_dir).name}-{pol.name}",
                            run_cfg.scene_preset, run_cfg.scenes_dir, run_cfg.scene_seed,
                            default_batch_size(params["base"], tpn_cfg), from_run=True)
    if run_dir is not None:
        pol, params, run_cfg = load_run_policy(run_dir, savn_act=savn_act)
        return LoadedPolicy(pol, params, Path(run_dir).name, run_cfg.scene_preset,
                            run_cfg.scenes_dir, run_cfg.scene_seed, from_run=True)
    if release_checkpoint is not None:
        if release_tpn:            # the test-time settings, checked before the file is read
            settings = get_tpn_config(**test_time).test_time()
        net = release.load(release_kind, release.read_checkpoint(release_checkpoint))
        stem = Path(release_checkpoint).stem
        if not release_tpn:
            name = f"{stem}-{release_kind}"
            return LoadedPolicy(model_policy(net.model, name, float(IMAGE_SIZE)), net.params,
                                name)
        # MetaMemoryGraphModel: its navigation network with the test-time updates of its
        # own TPN head (the release's procedure: tpn/test_time.py; tpn_lr 0: none)
        pol = tpn_policy(net.model, net.tpn, settings, tpn_name(release_kind, settings),
                         release.RELEASE_DROPOUT, box_scale=float(IMAGE_SIZE))
        params = {"base": net.params, "tpn": net.tpn_params}
        return LoadedPolicy(pol, params, f"{stem}-{pol.name}",
                            batch_size=default_batch_size(net.params, settings))
    policies = {"random": evaluation.random_policy, "expert": evaluation.expert_policy}
    name = policy or "random"
    if name not in policies:
        raise UserError(f"unknown policy {name!r}: expected one of {sorted(policies)}")
    return LoadedPolicy(policies[name](), None, name)


def is_results_json(path: str | Path) -> bool:
    """Whether `path` holds evaluation results this package wrote (a JSON object with
    "overall" and "per_room_type"); False for anything unreadable, binary or other."""
    try:
        with open(path, "rb") as f:
            if not f.read(64).lstrip().startswith(b"{"):
                return False
        doc = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and isinstance(doc.get("overall"), dict) \
        and isinstance(doc.get("per_room_type"), dict)


def run_scenes(loaded: LoadedPolicy, long: bool = False) -> str:
    """The scenes a loaded policy belongs to: its scene preset's name, or its scenes
    directory ('scene preset small' / 'scenes D' with long=True)."""
    if loaded.scenes_dir:
        return f"scenes {loaded.scenes_dir}" if long else str(loaded.scenes_dir)
    return f"scene preset {loaded.scene_preset}" if long else loaded.scene_preset


def evaluate(loaded: LoadedPolicy, split: str = "test", *, scenes_dir: str | None = None,
             scene_preset: str | None = None, episodes: str | None = None, episode_seed: int = 0,
             per_room_type: int = EPISODES_PER_ROOM_TYPE, seed: int = 0,
             batch_size: int | None = None, out: str | Path | None = None,
             progress: bool = True) -> dict:
    """Evaluate a loaded policy on a split's fixed episode set -> results dict (overall,
    per room type, per target, failure analysis; docs/evaluation.md) with the policy,
    split, scenes, episode_file and out. The episodes are replayed from `episodes` or
    sampled with episode_seed (and saved beside `out`); the results go to `out` (default
    runs/eval/<run>-<split>.json for a run on its own scenes, else
    runs/eval/<name>-<scenes>-<split>.json). Files that are not ours are never replaced.
    scene_preset: evaluate on this scene preset instead of the loaded policy's (a run on
    scenes other than its own, as scenes_dir does; its feature widths must be the run's);
    not with scenes_dir."""
    from tqdm import tqdm  # the progress bar: on first use, as the jax-based below
    from orgnav_jax import env, evaluation  # jax-based: on first use
    from orgnav_jax.episodes import (  # jax-based: on first use
        is_episode_file, load_episodes, sample_episodes, save_episodes)
    from orgnav_jax.scenes import device_split  # jax-based: on first use
    # jax-based: on first use
    from orgnav_jax.training.memory import available_memory, human
    if split not in ("train", "val", "test"):
        raise UserError(f"split {split!r}: expected train, val or test")
    if per_room_type < 1:
        raise UserError(f"--episodes-per-room-type {per_room_type}: expected an integer >= 1")
    if not episodes:
        need = per_room_type * len(ROOM_TYPES) * EPISODE_BYTES
        have, source = available_memory()
        if have is not None and need > have:
            raise UserError(f"--episodes-per-room-type {per_room_type:,}: ~{human(need)} of "
                            f"memory for {per_room_type * len(ROOM_TYPES):,} episodes; this "
                            f"machine has {human(have)} {source}")
    if batch_size is not None and batch_size < 1:
        raise UserError(f"--batch-size {batch_size}: expected an integer >= 1")
    if episode_seed < 0:
        raise UserError(f"--episode-seed {episode_seed}: expected an integer >= 0")
    for name, value in (("--out", out), ("--scenes", scenes_dir), ("--episodes", episodes)):
        if value is not None and not str(value).strip():
            raise UserError(f"{name} is empty: expected a path")
    if scene_preset is not None:
        if scenes_dir is not None:
            raise UserError(f"--scene-preset {scene_preset} and --scenes {scenes_dir}: give "
                            "one (the scenes to evaluate on)")
        if scene_preset != run_scenes(loaded):      # the run on scenes not its own
            loaded = dataclasses.replace(loaded, scene_preset=scene_preset, scenes_dir=None,
                                         from_run=False)
    own_scenes = loaded.from_run and scenes_dir is None
    scenes_dir = scenes_dir if scenes_dir is not None else loaded.scenes_dir
    tag = Path(scenes_dir).name if scenes_dir else loaded.scene_preset
    if out is None:
        out = (f"runs/eval/{loaded.name}-{split}.json" if own_scenes
               else f"runs/eval/{loaded.name}-{tag}-{split}.json")
    out = Path(out)
    ep_out = out.with_name(f"episodes-{tag}-{split}-seed{episode_seed}.json")
    check_output_file(out, is_results_json, RESULTS,
                      inputs=(episodes, None if episodes else ep_out))
    if not episodes:      # a sampled set is saved beside the results
        check_output_file(ep_out, is_episode_file, EPISODE_FILE,
                          option="the episode file beside --out")
    # the split on device, once per process (shared with training in the same process);
    # the set is memory-mapped and only this split's rooms are read
    scenes = device_split(loaded.scene_preset, loaded.scene_seed, scenes_dir, split)
    evaluation.check_scenes(loaded.policy, loaded.params, scenes)   # before any file
    if episodes:
        episode_set, ep_path = load_episodes(episodes, scenes), Path(episodes)
        if len(episode_set) == 0:
            raise ValueError(f"episode file {episodes} holds no episodes: nothing to "
                             "evaluate")
    else:
        episode_set = sample_episodes(scenes, per_room_type, seed=episode_seed, split=split)
        save_episodes(ep_out, episode_set, scenes)
        ep_path = ep_out
    with tqdm(total=len(episode_set), desc=f"evaluating {loaded.policy.name}", unit="ep",
              disable=not progress, file=sys.stderr) as bar:
        result = evaluation.evaluate(loaded.policy, loaded.params, scenes, episode_set,
                                     env.EnvParams.evaluation(), seed=seed,
                                     batch_size=(batch_size if batch_size is not None
                                                 else loaded.batch_size),
                                     progress=bar.update)
    result.update({"policy": loaded.name, "split": split, "scenes": tag,
                   "episode_file": str(ep_path), "out": str(out)})
    write_text_atomic(out, json_text(result))
    return result


def evaluate_policy(policy: str = "random", split: str = "test",
                    scene_preset: str = DEFAULT_SCENE_PRESET,
                    **kw) -> dict:
    """evaluate() of a named policy ('random', 'expert') on a preset or scenes_dir."""
    loaded = dataclasses.replace(load_policy(policy), scene_preset=scene_preset)
    return evaluate(loaded, split, **kw)


def load_run(run_dir: str | Path, savn_act: str | None = None, **test_time) -> LoadedPolicy:
    """The policy of a run directory: a training run's best-on-val model (savn_act
    overrides a SAVN run's test-time actions), or a stage-2 run's base with TPN's
    test-time updates (test_time: TEST_TIME_FIELDS overrides)."""
    config = Path(run_dir) / "config.json"
    try:
        stage = json.loads(config.read_text()).get("stage", "nav")
    except (OSError, ValueError, AttributeError, RecursionError):
        stage = "nav"                    # load_config names what is wrong
    if stage == "tpn":
        if savn_act is not None:
            raise UserError(f"--savn-act: {run_dir} is a TPN run: expected a SAVN or "
                            "D-SAVN run directory")
        return load_policy(tpn_dir=str(run_dir), **test_time)
    return load_policy(run_dir=str(run_dir), savn_act=savn_act, **test_time)


def evaluate_run(run_dir: str | Path, split: str = "test", **kw) -> dict:
    """evaluate() of a run directory's policy (load_run; kw may hold test-time fields
    for a TPN run)."""
    test_time = {k: kw.pop(k) for k in list(kw) if k in TEST_TIME_FIELDS}
    return evaluate(load_run(run_dir, savn_act=kw.pop("savn_act", None), **test_time),
                    split, **kw)


def train(cfg: TrainConfig, resume: bool = False, progress: bool = True) -> dict:
    """Stage 1: train (or resume) the navigation run cfg.run_dir -> summary (best val,
    env steps, compile and wall time; the final runner under 'runner')."""
    from orgnav_jax.training import loop  # jax-based: on first use
    return loop.train(cfg, resume=resume, progress=progress)


def train_seeds(cfg: TrainConfig, seeds, resume: bool = False, progress: bool = True,
                until_converged: bool = False) -> list[dict]:
    """Stage 1 for several seeds of cfg in one program (a vmapped population axis), seed
    S in <cfg.run_dir>-sS -> one summary per seed (training/loop.py: train_seeds).
    until_converged: stop at the first val evaluation where the convergence rule holds
    (tables/convergence.py; cfg.total_env_steps is then the cap; each summary's
    'stopped' says why it stopped early, None at the cap)."""
    from orgnav_jax.training import loop  # jax-based: on first use
    stop = None
    if until_converged:
        check_until_converged(cfg, seeds)
        stop = stop_when_converged()
    return loop.train_seeds(cfg, seeds, resume=resume, progress=progress, stop=stop)


def check_until_converged(cfg: TrainConfig, seeds) -> None:
    """UserError (one line) when the convergence rule cannot judge training cfg with
    these seeds (tables/convergence.py: check_stop_rule; SAVN trains one seed a program)."""
    try:
        check_stop_rule(list(seeds), cfg.eval_episodes_per_room_type)
    except ValueError as err:
        raise UserError(str(err)) from None
    if cfg.savn:
        raise UserError("--until-converged: SAVN runs train one seed per program "
                        "(docs/savn.md); the rule judges seeds trained together")


def pretrain(cfg, resume: bool = False, progress: bool = True) -> dict:
    """VTNet's pre-training: train (or resume) the visual transformer of the
    PretrainConfig cfg in cfg.run_dir -> summary (best val accuracy, samples;
    training/pretrain.py). A training run starts from it with pretrained=cfg.run_dir."""
    from orgnav_jax.training import pretrain as vtnet_pretraining  # jax-based: on first use
    return vtnet_pretraining.pretrain(cfg, resume=resume, progress=progress)


def pretrain_for(cfg: TrainConfig, pre_dir: str | Path, progress: bool = True) -> bool:
    """The pre-training a VTNet training config `cfg` starts from, in pre_dir (its
    PretrainConfig, seed cfg.seed): trained, resumed when partial, reused without work
    when finished -> whether any pre-training ran now."""
    from orgnav_jax.training.checkpoints import RunCheckpoints  # jax-based: on first use
    pcfg = PretrainConfig.of(cfg, run_dir=str(pre_dir), pretrained=None)
    resumed = is_run_dir(pre_dir)
    if resumed and (RunCheckpoints(pre_dir).latest_step() or 0) >= pcfg.total_samples:
        return False
    pretrain(pcfg, resume=resumed, progress=progress)
    return True


def train_tpn(cfg, resume: bool = False, progress: bool = True) -> dict:
    """Stage 2: train (or resume) the TPN of cfg.run_dir on its frozen base -> summary."""
    from orgnav_jax.tpn import stage2  # jax-based: on first use
    return stage2.train_tpn(cfg, resume=resume, progress=progress)


def test_run(run_dir: str | Path, progress: bool = True) -> dict:
    """The run's test-split evaluation, written to RUN_DIR/test_results.json."""
    return evaluate_run(run_dir, "test", out=Path(run_dir) / "test_results.json",
                        progress=progress)


def train_both(cfg: TrainConfig, resume: bool = False, progress: bool = True,
               test: bool = True, **tpn_fields) -> dict:
    """Both stages: the navigation run, then its TPN (in RUN_DIR/tpn; tpn_fields are
    TPNConfig fields such as tpn_lr, total_episodes), each tested on the test split when
    `test` -> {"nav": summary, "tpn": summary} (summaries hold "test" results)."""
    nav = train(cfg, resume=resume, progress=progress)
    if test:
        nav["test"] = test_run(cfg.run_dir, progress)["overall"]
    tpn_cfg = get_tpn_config(base_dir=cfg.run_dir, **tpn_fields)
    tpn = train_tpn(tpn_cfg, resume=resume and is_run_dir(tpn_cfg.run_dir),
                    progress=progress)
    if test:
        tpn["test"] = test_run(tpn_cfg.run_dir, progress)["overall"]
    return {"nav": nav, "tpn": tpn}


def resume_config(run_dir: str | Path, seeds=None, **changes) -> TrainConfig:
    """The saved config of a training run, in the directory given (a copied or moved run
    resumes where it is), with `changes` (budget, scenes_dir, devices) applied. With
    `seeds`, run_dir is a population's base (its runs are <run_dir>-s<seed>): the config
    of the first seed's run."""
    saved = run_dir
    if seeds:
        saved = seed_run_dir(str(run_dir), seeds[0])
    return dataclasses.replace(load_config(saved), run_dir=str(run_dir), **changes)
