"""Train a navigation agent: `python -m orgnav_jax.train`.

    python -m orgnav_jax.train                               # baseline, calibrated benchmark
    python -m orgnav_jax.train --preset small --model we --run-dir runs/we
    python -m orgnav_jax.train --run-dir runs/baseline-calibrated --resume
    python -m orgnav_jax.train --stage tpn --base runs/baseline-calibrated   # stage 2: TPN
    python -m orgnav_jax.train --preset full      # ORG + IL, then its TPN: the full model
    python -m orgnav_jax.train --preset vtnet     # VTNet: pre-training, then A2C from it
    python -m orgnav_jax.train --stage pretrain --preset vtnet --run-dir runs/vt-pre

With no arguments it builds (or reuses) the calibrated benchmark (the default scene
preset), trains the Baseline for the default budget in runs/baseline-calibrated,
evaluates the best-on-val checkpoint on the test split (250 episodes per room type) and
prints the Table-1-style row, `baseline-calibrated`. A run goes to runs/<preset>, with
-<scenes> where --scene-preset or --scenes-dir is not the preset's own (runs/we-small). Every
TrainConfig field is an option; see --help.

`--preset vtnet` pre-trains VTNet's visual transformer on the expert's actions (a run in
RUN_DIR-pretrain; per seed RUN_DIR-pretrain-sS), then trains it by A2C from the result
(docs/vtnet.md); `--stage pretrain` runs the pre-training alone (its options are the
training options: the pretrain_* fields, the model's widths; default preset vtnet, run
directory <the preset's>-pretrain), and `--pretrained PRE_RUN_DIR` starts a VTNet run from
one (with --seeds: PRE_RUN_DIR-sS for seed S).

`--stage tpn --base RUN_DIR` trains the tentative policy network on the frozen model of a
finished run (stage 2; by default in RUN_DIR/tpn), then evaluates the model with TPN's
test-time updates on the test split. Its options are the TPNConfig fields: see
`python -m orgnav_jax.train --stage tpn --help`.

Scale-out (docs/scale_out.md):
    python -m orgnav_jax.train --devices 2                # env axis over 2 devices
    python -m orgnav_jax.train --seeds 0 1 2              # 3 seeds in one program:
                                                          #   RUN_DIR-s0, -s1, -s2
    python -m orgnav_jax.train --budget paper             # 6 M episodes (96 M env steps)
    python -m orgnav_jax.train --dtype bfloat16           # bf16 matmuls, fp32 parameters
    python -m orgnav_jax.train --coordinator HOST:PORT --num-processes 2 --process-id 0
    srun python -m orgnav_jax.train --distributed         # processes from the launcher
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax

from orgnav_jax import api, evaluate
from orgnav_jax.errors import UserError, run_cli
from orgnav_jax.tpn.config import (
    add_tpn_arguments, check_tpn_base, get_tpn_config, load_tpn_config,
    tpn_overrides_from_args)
from orgnav_jax.training.config import (
    BUDGETS, TRAIN_PRESETS, PretrainConfig, add_config_arguments, default_run_dir, get_config,
    load_config, load_pretrain_config, overrides_from_args)
from orgnav_jax.training.run_dir import is_run_dir, seed_run_dir
from orgnav_jax.training.scale import DISTRIBUTED_TIMEOUT_S, init_distributed, is_primary


def _parser(prog: str, stage: str) -> argparse.ArgumentParser:
    """The options both stages share."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stage", choices=STAGES, default=stage,
                    help="nav: train a navigation model (stage 1); tpn: stage 2; pretrain: "
                         "VTNet's pre-training (see above)")
    ap.add_argument("--resume", action="store_true",
                    help="continue the run in --run-dir from its latest checkpoint")
    ap.add_argument("--no-test", action="store_true", help="skip the final test evaluation")
    ap.add_argument("--quiet", action="store_true", help="no progress bars")
    ap.add_argument("--budget", choices=sorted(BUDGETS), default=None,
                    help="a named training budget: paper = the paper's 6 M episodes for "
                         "stage 1 (96 M env steps: 16 env steps per episode, measured) and "
                         "2 M episodes for the TPN (docs/scale_out.md)")
    procs = ap.add_argument_group(
        "several processes (jax.distributed; process 0 writes the logs; docs/scale_out.md)")
    procs.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                       help="address of process 0's coordinator service")
    procs.add_argument("--num-processes", type=int, default=None, metavar="P")
    procs.add_argument("--process-id", type=int, default=None, metavar="I")
    procs.add_argument("--distributed", action="store_true",
                       help="jax.distributed.initialize() with the launcher's settings "
                            "(Slurm, Open MPI, or JAX_COORDINATOR_ADDRESS etc.)")
    procs.add_argument("--distributed-timeout", type=int, default=None, metavar="S",
                       help="seconds to wait for the coordinator and the other processes "
                            "(default 300), then stop with an error")
    return ap


STAGES = ("nav", "tpn", "pretrain")
# options that may go with --resume --run-dir alone (the rest come from config.json)
RESUME_OPTIONS = {"run_dir", "total_env_steps", "scenes_dir", "devices", "pretrained",
                  "word_vectors"}     # (a moved file: its vectors must be the run's)
RESUME_PRETRAIN_OPTIONS = {"run_dir", "pretrain_samples", "scenes_dir", "devices"}
RESUME_TPN_OPTIONS = {"run_dir", "total_episodes", "base_dir"}

# presets that run both stages: the navigation preset, then its TPN, evaluated with the
# test-time learning rate chosen on val (tpn.config.TPN_LR; README, Tables 1-2)
TPN_PIPELINES = {"baseline_tpn": "baseline", "full": "org_il"}
# presets that pre-train first (VTNet, issue 43) unless --pretrained names a pre-training
PRETRAIN_PIPELINES = ("vtnet",)
PRETRAIN_PRESET = "vtnet"     # --stage pretrain's default preset
DEFAULT_PRESET = "small"      # --preset when none is given (None: a resume keeps the run's)


def parser() -> argparse.ArgumentParser:
    ap = _parser("python -m orgnav_jax.train", "nav")
    ap.add_argument("--preset", default=None, choices=sorted(TRAIN_PRESETS) + sorted(TPN_PIPELINES),
                    help=f"a training preset (default {DEFAULT_PRESET}: the Baseline, in "
                         "runs/baseline-<scenes>); baseline_tpn and full "
                         "(ORG + IL + TPN) also train the TPN (stage 2) on the result; with "
                         "--resume it must agree with the run's saved config")
    ap.add_argument("--tpn-lr", type=float, default=None,
                    help="baseline_tpn / full: test-time learning rate (default: the one "
                         "val chose, 1e-3; 0: no test-time update)")
    ap.add_argument("--tpn-episodes", type=int, default=None,
                    help="baseline_tpn / full: stage-2 training episodes (default 40000)")
    ap.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                    help="train these seeds of the config in one program (a vmapped "
                         "population axis), seed S in RUN_DIR-sS (instead of --seed)")
    ap.add_argument("--until-converged", action="store_true",
                    help="with --seeds (2 or more) and --eval-episodes-per-room-type 250: "
                         "stop at the first val evaluation where the convergence rule "
                         "holds (docs/results.md); --total-env-steps is then the cap")
    add_config_arguments(ap)
    return ap


def tpn_parser() -> argparse.ArgumentParser:
    ap = _parser("python -m orgnav_jax.train --stage tpn", "tpn")
    add_tpn_arguments(ap)
    return ap


def main_tpn(argv: list[str]) -> dict:
    """Stage 2: train the TPN on a finished run, then evaluate with test-time updates."""
    args = tpn_parser().parse_args(argv)
    if start_processes(args) > 1:
        raise UserError("--stage tpn runs in one process: start it without --coordinator / "
                        "--distributed (stage 2 is small; its base may come from a "
                        "multi-process run)")
    fields = tpn_overrides_from_args(args)
    if args.budget:
        if "total_episodes" in fields:
            raise UserError("--budget and --total-episodes set the same budget: give one")
        fields["total_episodes"] = BUDGETS[args.budget].tpn_episodes
    if args.resume and "run_dir" in fields and not (set(fields) - RESUME_TPN_OPTIONS):
        # resume with the saved config, in the directory given (a copied or moved run)
        cfg = dataclasses.replace(load_tpn_config(fields["run_dir"]), **fields)
        if not Path(cfg.base_dir).exists():
            raise UserError(f"--resume {cfg.run_dir}: its base run {cfg.base_dir} does not "
                            "exist (moved?); add --base NEW_BASE_DIR")
    else:
        if not fields.get("base_dir"):
            raise UserError("--stage tpn needs --base RUN_DIR (a finished training run)")
        base = load_config(fields["base_dir"])   # a training run (clear errors otherwise)
        check_tpn_base(base, fields["base_dir"])    # not SAVN: one line, nothing written
        cfg = get_tpn_config(**fields)
    return run_tpn_stage(cfg, args.resume, args)


def start_processes(args) -> int:
    """jax.distributed.initialize when asked (before anything touches a device) -> the
    number of processes."""
    timeout = args.distributed_timeout
    if timeout is not None and timeout < 1:
        raise UserError(f"--distributed-timeout {timeout}: expected an integer >= 1 (seconds)")
    if args.coordinator is not None and not args.coordinator.strip():
        raise UserError("--coordinator is empty: expected HOST:PORT")
    init_distributed(args.coordinator, args.num_processes, args.process_id,
                     auto=args.distributed,
                     timeout_s=DISTRIBUTED_TIMEOUT_S if timeout is None else timeout)
    if args.coordinator is not None or args.distributed:
        return jax.process_count()
    return 1


def primary() -> bool:
    """Whether this process prints and writes results (process 0; see training/scale.py)."""
    return is_primary()


def announce(cfg, header: str) -> None:
    """The budget notice (if the budget rounds) and the run's one-line header."""
    if not primary():
        return
    if cfg.budget_notice():
        print(cfg.budget_notice(), file=sys.stderr, flush=True)
    print(header, flush=True)


def finish(summary: dict, run_dir: str, args) -> dict:
    """Print the summary; unless --no-test, evaluate the run on the test split (in one
    process: a multi-process run skips it, see docs/scale_out.md)."""
    summary.pop("runner")
    if not primary():
        return summary
    print(json.dumps(summary, default=str))
    if not args.no_test and jax.process_count() > 1:
        print(f"note: no test evaluation in a multi-process run; evaluate it in one process: "
              f"python -m orgnav_jax.evaluate --checkpoint {run_dir} --split test",
              file=sys.stderr, flush=True)
    elif not args.no_test:
        result = api.test_run(run_dir, progress=not args.quiet)
        evaluate.print_results(result["policy"], result)
        print(f"\nresults: {result['out']}")
        summary["test"] = result["overall"]
    return summary


def run_tpn_stage(cfg, resume: bool, args) -> dict:
    announce(cfg, f"TPN run {cfg.run_dir}: base {cfg.base_dir}, {cfg.num_envs} episodes x "
                  f"{cfg.episode_cap} steps per update, {cfg.total_episodes:,} episodes, "
                  f"deadlock detector {cfg.deadlock}")
    return finish(api.train_tpn(cfg, resume=resume, progress=not args.quiet), cfg.run_dir,
                  args)


def nav_config(args, processes: int = 1):
    """The stage-1 TrainConfig the parsed options ask for (preset, fields, --budget, or
    the saved config of a run to --resume); UserError for options that do not go
    together."""
    overrides = overrides_from_args(args)
    pipeline = TPN_PIPELINES.get(args.preset)
    if (args.tpn_lr is not None or args.tpn_episodes is not None) and not pipeline:
        raise UserError(f"--tpn-lr and --tpn-episodes go with the presets "
                        f"{sorted(TPN_PIPELINES)}")
    if args.seeds is not None and "seed" in overrides:
        raise UserError("--seed and --seeds: give one")
    if args.budget:
        if "total_env_steps" in overrides:
            raise UserError("--budget and --total-env-steps set the same budget: give one")
        overrides["total_env_steps"] = BUDGETS[args.budget].env_steps
    if processes > 1 and pipeline:
        raise UserError(f"--preset {args.preset} trains the TPN too, which runs in one "
                        f"process: train --preset {pipeline} on several processes, then "
                        "--stage tpn --base RUN_DIR in one")
    if args.resume and "run_dir" in overrides and not (set(overrides) - RESUME_OPTIONS):
        # resume with the saved config, in the directory given (a copied or moved run);
        # the budget may be extended, the scenes moved and the devices changed
        cfg = api.resume_config(seeds=args.seeds, **overrides)
        if args.preset is not None:
            check_resume_preset(args.preset, cfg)
        return cfg
    preset = args.preset or DEFAULT_PRESET
    if pipeline:
        overrides.setdefault("run_dir", default_run_dir(preset, overrides))
    return get_config(pipeline or preset, **overrides)


def check_resume_preset(preset: str, cfg) -> None:
    """--resume continues a run with its saved config: a --preset given with it must
    agree with that config on the fields the preset sets (UserError naming them, before
    anything is written), rather than being ignored without a word."""
    name = TPN_PIPELINES.get(preset, preset)
    want = get_config(name)
    keys = (set(TRAIN_PRESETS[name]) | {"model", "il", "savn"}) - RESUME_OPTIONS
    if cfg.model != "vtnet":      # VTNet's widths (the paper preset's) mean nothing else
        keys = {k for k in keys if not k.startswith("vtnet_")}
    differ = sorted(k for k in keys if getattr(cfg, k) != getattr(want, k))
    if differ:
        saved = ", ".join(f"{k} {getattr(cfg, k)!r}" for k in differ)
        raise UserError(f"--preset {preset}: {cfg.run_dir} was trained with {saved}, not "
                        f"what the preset sets; --resume continues a run with its saved "
                        "config: drop --preset")


def pipeline_tpn_fields(args) -> dict:
    """The TPN fields of a both-stages preset (--tpn-lr, --tpn-episodes or --budget),
    validated before stage 1 trains: ValueError naming the field otherwise."""
    fields = {} if args.tpn_lr is None else {"tpn_lr": args.tpn_lr}
    episodes = args.tpn_episodes if args.tpn_episodes is not None else (
        BUDGETS[args.budget].tpn_episodes if args.budget else None)
    if episodes is not None:
        fields["total_episodes"] = episodes
    try:
        get_tpn_config(base_dir="(the stage-1 run)", **fields)
    except ValueError as err:
        raise UserError(str(err).replace("TPN config field 'tpn_lr'", "--tpn-lr")
                        .replace("TPN config field 'total_episodes'", "--tpn-episodes"))
    return fields


def main(argv: list[str] | None = None) -> dict:
    argv = sys.argv[1:] if argv is None else list(argv)
    stage = argparse.ArgumentParser(add_help=False)
    stage.add_argument("--stage", choices=STAGES, default="nav")
    which = stage.parse_known_args(argv)[0].stage
    if which == "tpn":
        return main_tpn(argv)
    args = parser().parse_args(argv)
    if args.until_converged and (which == "pretrain" or args.seeds is None or
                                 args.preset in PRETRAIN_PIPELINES):
        raise UserError("--until-converged goes with stage-1 training of --seeds S1 S2 ... "
                        "in one program (not pre-training)")
    if which == "pretrain":
        return main_pretrain(args)
    if args.preset in PRETRAIN_PIPELINES and "pretrained" not in overrides_from_args(args):
        return main_pretrain_pipeline(args)
    pipeline = TPN_PIPELINES.get(args.preset)
    tpn_fields = pipeline_tpn_fields(args) if pipeline else {}      # before any work
    cfg = nav_config(args, processes=start_processes(args))
    if args.until_converged:
        api.check_until_converged(cfg, args.seeds)
    seeds = f", seeds {' '.join(map(str, args.seeds))} in one program" if args.seeds else ""
    shape = (f"SAVN, {cfg.num_envs} rows x {cfg.savn_segments} segments x {cfg.savn_steps} "
             "steps" if cfg.savn else f"{cfg.num_envs} envs x {cfg.rollout_len} steps")
    announce(cfg, f"run {cfg.run_dir}: model {cfg.model}, IL {cfg.il}, scenes "
                  f"{cfg.scenes_dir or cfg.scene_preset}, {shape}, "
                  f"{cfg.total_env_steps:,} env steps{seeds}")
    if args.budget and primary():
        print(BUDGETS[args.budget].describe(), file=sys.stderr, flush=True)
    if args.seeds is not None:
        runs = api.train_seeds(cfg, args.seeds, resume=args.resume, progress=not args.quiet,
                               until_converged=args.until_converged)
        summaries = [finish(s, s["run_dir"], args) for s in runs]
    else:
        summaries = [finish(api.train(cfg, resume=args.resume, progress=not args.quiet),
                            cfg.run_dir, args)]
    if pipeline:
        for summary in summaries:
            tpn_cfg = get_tpn_config(base_dir=summary["run_dir"], **tpn_fields)
            summary["tpn"] = run_tpn_stage(
                tpn_cfg, args.resume and is_run_dir(tpn_cfg.run_dir), args)
    return summaries[0] if args.seeds is None else {"runs": summaries}


def pretrain_configs(args, nav=None) -> list:
    """The PretrainConfigs --stage pretrain (or a pre-training pipeline, of the training
    config `nav`) runs: one, or one per --seeds seed (RUN_DIR-sS); UserError for options
    that do not go together."""
    fields = overrides_from_args(args)
    seeds = args.seeds
    if seeds is not None and "seed" in fields:
        raise UserError("--seed and --seeds: give one")
    if nav is None and args.resume and "run_dir" in fields and \
            not (set(fields) - RESUME_PRETRAIN_OPTIONS):
        first = seed_run_dir(fields["run_dir"], seeds[0]) if seeds else fields["run_dir"]
        saved = load_pretrain_config(first)
        base, run_dir = dataclasses.replace(saved, run_dir=fields["run_dir"]), fields["run_dir"]
        base = dataclasses.replace(base, **{k: v for k, v in fields.items() if k != "run_dir"})
    else:
        if nav is None:
            preset = args.preset or PRETRAIN_PRESET
            if preset not in TRAIN_PRESETS:
                raise UserError(f"--stage pretrain --preset {preset}: expected a training "
                                f"preset of model vtnet (e.g. {PRETRAIN_PRESET})")
            if args.budget:
                raise UserError("--budget sets the training budgets; pre-training's is "
                                "--pretrain-samples")
            run_dir = fields.pop("run_dir", f"{default_run_dir(preset, fields)}-pretrain")
            nav = get_config(preset, **fields)
        else:
            run_dir = f"{str(nav.run_dir).rstrip('/')}-pretrain"
        base = nav
    if seeds is None:
        return [PretrainConfig.of(base, run_dir=run_dir, pretrained=None)]
    if len(set(seeds)) != len(seeds):
        raise UserError(f"--seeds {' '.join(map(str, seeds))}: expected distinct seeds")
    return [PretrainConfig.of(base, run_dir=seed_run_dir(run_dir, s), seed=s,
                              pretrained=None) for s in seeds]


def run_pretrain(cfgs: list, resume: bool, args) -> list[dict]:
    """Pre-train each config in turn (resuming the runs that exist when `resume`) ->
    their summaries (printed as JSON lines)."""
    out = []
    for cfg in cfgs:
        announce(cfg, f"pre-training {cfg.run_dir}: VTNet, {cfg.pretrain_samples:,} samples "
                      f"in batches of {cfg.pretrain_batch}, seed {cfg.seed}")
        summary = api.pretrain(cfg, resume=resume and is_run_dir(cfg.run_dir),
                               progress=not args.quiet)
        summary.pop("runner")
        if primary():
            print(json.dumps(summary, default=str), flush=True)
        out.append(summary)
    return out


def main_pretrain(args) -> dict:
    """--stage pretrain: VTNet's pre-training alone (training/pretrain.py)."""
    if start_processes(args) > 1:
        raise UserError("--stage pretrain runs in one process")
    if args.tpn_lr is not None or args.tpn_episodes is not None:
        raise UserError("--tpn-lr and --tpn-episodes go with the presets "
                        f"{sorted(TPN_PIPELINES)}")
    summaries = run_pretrain(pretrain_configs(args), args.resume, args)
    return summaries[0] if args.seeds is None else {"runs": summaries}


def main_pretrain_pipeline(args) -> dict:
    """--preset vtnet: the pre-training (RUN_DIR-pretrain), then the training run from it
    (each tested unless --no-test). A --resume continues whichever stage was running."""
    if start_processes(args) > 1:
        raise UserError(f"--preset {args.preset} pre-trains first, in one process: run "
                        "--stage pretrain, then --pretrained PRE_RUN_DIR on several")
    fields = overrides_from_args(args)
    run_dir = fields.get("run_dir", default_run_dir(args.preset, fields))
    first = seed_run_dir(run_dir, args.seeds[0]) if args.seeds else run_dir
    pre_dir = f"{str(run_dir).rstrip('/')}-pretrain"
    pre_first = seed_run_dir(pre_dir, args.seeds[0]) if args.seeds else pre_dir
    if args.resume and not is_run_dir(first) and not is_run_dir(pre_first):
        # nothing of the pipeline exists (a mistyped --run-dir): refused as every preset's
        # --resume is, rather than starting hours of pre-training and training anew
        raise FileNotFoundError(f"--resume: {first} holds no run, nor {pre_first} a "
                                "pre-training (config.json is missing or not a run "
                                "config): nothing to resume; drop --resume to start one")
    if args.resume and is_run_dir(first):      # pre-training done: training resumes
        cfg = nav_config(args)
        if cfg.pretrained is None:     # options beside --run-dir: the preset's config
            cfg = dataclasses.replace(cfg, pretrained=f"{str(run_dir).rstrip('/')}-pretrain")
        pre = []
    else:
        cfg = nav_config(argparse.Namespace(**{**vars(args), "resume": False}))
        pre = run_pretrain(pretrain_configs(args, cfg), args.resume, args)
        cfg = dataclasses.replace(cfg, pretrained=f"{str(cfg.run_dir).rstrip('/')}-pretrain")
    announce(cfg, f"run {cfg.run_dir}: model {cfg.model} from pre-training {cfg.pretrained}, "
                  f"{cfg.num_envs} envs x {cfg.rollout_len} steps, "
                  f"{cfg.total_env_steps:,} env steps")
    resume = args.resume and is_run_dir(first)
    if args.seeds is not None:
        runs = api.train_seeds(cfg, args.seeds, resume=resume, progress=not args.quiet)
        summaries = [finish(s, s["run_dir"], args) for s in runs]
    else:
        summaries = [finish(api.train(cfg, resume=resume, progress=not args.quiet),
                            cfg.run_dir, args)]
    for summary, p in zip(summaries, pre):
        summary["pretrain"] = p
    return summaries[0] if args.seeds is None else {"runs": summaries}


if __name__ == "__main__":
    sys.exit(run_cli(main))
