"""Benchmark: training env-steps/s of the jitted chunk (rollout + A2C update), per model.

    python benchmarks/train_throughput.py                         # every model, small+paper
    python benchmarks/train_throughput.py --models baseline --num-envs 16 64
    python benchmarks/train_throughput.py --presets paper --updates-per-chunk 3
    python benchmarks/train_throughput.py --models baseline --devices 1 2   # data parallel
    python benchmarks/train_throughput.py --models baseline --seeds 1 3     # population

For each model in `orgnav_jax.models.ENCODERS`, each training preset (`small`, `paper`
widths) and each number of envs N, it compiles `make_train_chunk` (updates_per_chunk x
(rollout of rollout_len steps + gradient step) under one jit) and times it:

* compile_s: trace + lower + XLA compile (`.trace(...).lower().compile()`), timed apart;
* env_steps_per_s: updates_per_chunk * N * rollout_len env-steps over the best of
  --repeats runs of the compiled chunk (the same start state every run);
* flops_per_env_step, gflops_per_s: see "FLOPs" below;
* scratch_mb: XLA's temporary buffers of the compiled chunk (memory_analysis());
* matmul_peak_gflops: a jitted float32 (2048x2048)@(2048x2048) matmul, best of several,
  measured before and after the rows (the larger kept: the machine may be shared).

Scale-out (docs/scale_out.md). --devices D shards the env axis over D devices
(training/scale.py; N must divide by D); --seeds S vmaps the chunk over S seeds (one
program, S x the env-steps per chunk). Every combination of --devices and --seeds is a
row. On CPU, devices beyond one are forced host devices: the script sets
XLA_FLAGS=--xla_force_host_platform_device_count=max(--devices) before importing jax,
and the forced devices share the machine's cores (no faster than one device there).

SAVN (--savn also | first-order; training/savn.py, docs/savn.md). After each model's row, a
row of SAVN training of that model: its env_steps_per_s counts the env steps the episodes
really took (a row whose episode ended idles to the next segment boundary, where it
starts a new one), slot_steps_per_s every row step, real_fraction the share of real ones,
ratio_to_base the real env-steps/s over the base model's (the plain A2C row, timed again
after the SAVN rows, best of all its runs kept: every step of A2C is real),
flops_per_row_step the scan-aware FLOP count of the chunk per row step. One untimed
chunk runs first so that the timed ones start with episodes running in the rows. Both
rows are timed on the SAVN rows' network, one LSTM layer (TABLE_ROWS["dsavn"], as SAVN's
release), unless --lstm-layers N says otherwise (it sets the depth of every row).
--savn-segments U [U ...] times a row per savn_segments. How much of SAVN's time is idle
depends on how long its episodes are: a fresh policy says Done after about 6.5 steps, a
trained agent walks 15-18. --params-from RUN_DIR [RUN_DIR ...] times each run's model at
its widths on its training rooms from its best-on-val parameters instead of the presets
(a plain run: its network, SAVN's learned loss fresh; a SAVN run: both; the base model's
row gets the same network):

    python benchmarks/train_throughput.py --num-envs 64 --updates-per-chunk 2 --repeats 3 \
        --savn also --params-from runs/dsavn runs/savn

Scenes. The benchmark does not build the `paper` scene preset (minutes, > 1 GB): it loads
the `tiny` preset once (cached after the first ~20 s build) and swaps in the feature
projections of each training preset's scene preset (`scenes.synthetic.builder.feature_bases`: the
same arrays a real build of that preset uses), so the decoded widths are the preset's
(paper: 7x7x512 global map, 22x512 appearance) and every step does the same work as on
the real set; only the number of rooms differs, and the model only gathers from them.

FLOPs. XLA's cost analysis (`compiled.cost_analysis()`, a dict in jax 0.10 with key
'flops'; older versions return a list of one dict, both are accepted) counts the body of
a while loop once, not times its trip count: the chunk is a scan over updates whose body
holds the rollout scan, the GAE scan and the replay scan plus its transpose, so the raw
number is roughly one env-step of each, whatever rollout_len and updates_per_chunk are
(checked: a 10-step scan of a matmul reports the flops of one matmul). So FLOPs are
counted scan-aware on the chunk's jaxpr:

    flops(jaxpr) = hlo(jaxpr) + sum over scans s in it of (length_s * flops(body_s) - hlo(body_s))

where hlo() is XLA's cost analysis of the jaxpr lowered as its own program (the
pre-optimisation HLO analysis, `Lowered.cost_analysis()`, which needs no compile), and
the scans are found through nested jit / custom-derivative calls. Divided by the chunk's
env-steps. Why the pre-optimisation HLO: for a scanned chunk it agrees with the compiled
analysis to < 0.1 % (paper widths, N=16, T=2: 1727.5 vs 1728.6 MFLOP raw), while compiling a
fully unrolled chunk instead would let XLA merge the replay's forward pass with the
identical rollout forward (no dropout, same parameters) and under-count the work the real,
scanned program does by about a quarter. The table also shows the raw compiled count
("xla raw") so the difference stays visible.

Check against a hand count, paper widths (per env-step, forward): LSTM 4*512*(3136+512)*2
= 14.9 MFLOP, global 1x1 49*512*64*2 = 3.2, Baseline encoder 22*518*49*2 = 1.1, fuse 1x1
0.6, feature decode 0.8 -> ~20.7 MFLOP; training = rollout forward + replay forward +
backward (~35: weight and input gradients of the LSTM and fuse layer, weight gradients
only below) ~ 77 MFLOP, plus the Adam step per update. The scan-aware count gives 77.7
MFLOP per env-step plus ~484 MFLOP per update at N=16 (79.6 per env-step at T=16), the same
as XLA's analysis of the fully unrolled (lowered, not optimised) chunk at T = 1, 2, 4.

Prints a table, then one JSON object as the last line:
{"results": [{"preset", "model", "num_envs", "devices", "seeds", "env_steps_per_s",
"compile_s", "gflops_per_s", "flops_per_env_step"}, ...], "matmul_peak_gflops": ...}
A model's row timed beside a Baseline row (same preset, N, devices, seeds, dtype) also
has "ratio_to_baseline": its env-steps/s over the Baseline's, after --ratio-rounds rounds
of timing the two in turn (VTNet at small widths: docs/vtnet.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path


def _force_host_devices(argv: list[str]) -> None:
    """XLA_FLAGS for max(--devices) host devices, before jax is imported (CPU only; a
    GPU backend ignores the flag)."""
    if "--devices" not in argv:
        return
    wanted = []
    for a in argv[argv.index("--devices") + 1:]:
        if a.startswith("-"):
            break
        wanted.append(int(a) if a.isdigit() else 1)
    flags = os.environ.get("XLA_FLAGS", "")
    if wanted and max(wanted) > 1 and "xla_force_host_platform_device_count" not in flags:
        os.environ["XLA_FLAGS"] = (flags + " --xla_force_host_platform_device_count="
                                   f"{max(wanted)}").strip()


_force_host_devices(sys.argv[1:])

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
from jax.extend.core import jaxpr_as_fun  # noqa: E402

from orgnav_jax.models import ENCODERS, build_model  # noqa: E402
from orgnav_jax.scenes import load_or_build  # noqa: E402
from orgnav_jax.scenes.synthetic.builder import feature_bases  # noqa: E402
from orgnav_jax.scenes.synthetic.presets import get_preset  # noqa: E402
from orgnav_jax.training import scale  # noqa: E402
from orgnav_jax.training.config import TABLE_ROWS, get_config, load_config  # noqa: E402
from orgnav_jax.training.update import (  # noqa: E402
    init_runner, make_optimizer, make_train_chunk)


# --------------------------------------------------------------------------- FLOPs
def _flops(cost) -> float:
    """'flops' from a cost analysis: a dict (jax >= 0.4.30) or a list of dicts (older);
    NaN where XLA gives none (on an H200 with jax 0.11.2 it did not: the rows then show
    "-" for the FLOP columns instead of stopping the benchmark, time_row)."""
    if cost is None:
        return float("nan")
    if isinstance(cost, (list, tuple)):
        return float(sum(c.get("flops", 0.0) for c in cost))
    return float(cost.get("flops", 0.0))


def _per_step(flops: float, steps: int, scale: float = 1.0, digits: int | None = None):
    """flops / steps / scale rounded, or None where the count is unknown (not finite)."""
    return round(flops / steps / scale, digits) if math.isfinite(flops) else None


def _col(value, width: int, scale: float = 1.0) -> str:
    """A table cell: value / scale with 2 decimals, or "-" for an unknown (None)."""
    return f"{value / scale:{width}.2f}" if value is not None else f"{'-':>{width}}"


def _sub_jaxprs(eqn):
    for v in eqn.params.values():
        for x in (v if isinstance(v, (list, tuple)) else (v,)):
            if hasattr(x, "jaxpr") and hasattr(x, "consts"):   # ClosedJaxpr
                yield x.jaxpr
            elif hasattr(x, "eqns"):                             # Jaxpr
                yield x


def _loops(jaxpr):
    """Scan / while equations of `jaxpr`, looking through nested calls but not into loops."""
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in ("scan", "while"):
            yield eqn
        else:
            for sub in _sub_jaxprs(eqn):
                yield from _loops(sub)


def _hlo_flops(closed) -> float:
    """XLA's (pre-optimisation) cost analysis of a closed jaxpr lowered on its own."""
    args = [jax.ShapeDtypeStruct(v.aval.shape, v.aval.dtype) for v in closed.jaxpr.invars]
    return _flops(jax.jit(jaxpr_as_fun(closed)).lower(*args).cost_analysis())


def scan_aware_flops(closed, hlo_top: float | None = None) -> float:
    """FLOPs of a closed jaxpr with every scan body counted `length` times (see module
    docstring). `hlo_top`: the top level's cost analysis if already known."""
    total = _hlo_flops(closed) if hlo_top is None else hlo_top
    for eqn in _loops(closed.jaxpr):
        if eqn.primitive.name == "while":   # trip count unknown: counted once, as XLA does
            print("warning: a while_loop body is counted once in the FLOPs", flush=True)
            continue
        body = eqn.params["jaxpr"]
        total += eqn.params["length"] * scan_aware_flops(body) - _hlo_flops(body)
    return total


# --------------------------------------------------------------------------- scenes
def bench_scenes(base, preset: str):
    """The tiny train scenes with the feature projections of `preset`'s scene preset."""
    widths = get_preset(get_config(preset).scene_preset)
    scenes = base.replace(**feature_bases(widths)).to_device()
    assert scenes.global_dim == widths.global_dim, (scenes.global_dim, widths)
    assert scenes.appearance_dim == widths.appearance_dim, (scenes.appearance_dim, widths)
    return scenes


# --------------------------------------------------------------------------- timing
def scratch_mb(compiled) -> float:
    """XLA's temporary buffers of a compiled program, MB (compiled.memory_analysis():
    what the program allocates beyond its arguments and outputs)."""
    return round(compiled.memory_analysis().temp_size_in_bytes / 1e6, 1)


def row_config(preset: str, trained: "Trained | None" = None, **over):
    """The config of a row: the preset's, or a trained run's (its model and widths) with
    savn False, fields replaced."""
    if trained is None:
        return get_config(preset, **over)
    return dataclasses.replace(trained.cfg, **{"savn": False, **over}).validate()


def time_row(preset: str, model_name: str, num_envs: int, scenes, updates: int,
             rollout_len: int | None, repeats: int, devices: int = 1, seeds: int = 1,
             dtype: str = "float32", trained: "Trained | None" = None,
             lstm_layers: int | None = None) -> dict:
    over = dict(model=model_name, num_envs=num_envs, updates_per_chunk=updates, dtype=dtype)
    if lstm_layers:
        over["lstm_layers"] = lstm_layers
    if rollout_len:
        over["rollout_len"] = rollout_len
    cfg = row_config(preset, trained, **over)
    skip = memory_skip(cfg, scenes, seeds)
    if skip:
        return {"preset": preset, "model": model_name, "num_envs": num_envs,
                "devices": devices, "seeds": seeds, "dtype": dtype, **skip}
    model = build_model(cfg, scenes)
    optimizer = make_optimizer(cfg)
    runners = [init_runner(cfg, model, optimizer, scenes, jax.random.PRNGKey(cfg.seed + i))
               for i in range(seeds)]
    if trained is not None:            # the run's parameters (its navigation network)
        runners = [r.replace(params=trained.nav) for r in runners]
    runner = (jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *runners) if seeds > 1
              else runners[0])
    mesh = scale.make_mesh(devices)
    scale.check_batch(num_envs, mesh)
    if mesh is not None:
        runner = scale.place(runner, scale.runner_shardings(runner, mesh, seeds > 1))
        scenes = scale.place(scenes, scale.replicated(scenes, mesh))
    jax.block_until_ready(runner)
    chunk = make_train_chunk(cfg, model, optimizer, mesh=mesh, population=seeds > 1)

    t0 = time.perf_counter()
    traced = chunk.trace(runner, scenes)
    lowered = traced.lower()
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0

    def timed(repeats: int) -> float:
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(runner, scenes))
            best = min(best, time.perf_counter() - t0)
        return best

    best = timed(repeats)
    steps = cfg.updates_per_chunk * cfg.num_envs * cfg.rollout_len * seeds
    flops = scan_aware_flops(traced.jaxpr, _flops(lowered.cost_analysis()))
    raw = _flops(compiled.cost_analysis())
    sps = steps / best
    return {"preset": preset, "model": model_name, "num_envs": num_envs,
            "lstm_layers": cfg.lstm_layers,
            "devices": scale.mesh_size(mesh), "seeds": seeds, "dtype": dtype,
            "env_steps_per_s": round(sps, 1), "compile_s": round(compile_s, 2),
            "gflops_per_s": _per_step(flops * sps, steps, 1e9, 2),
            "flops_per_env_step": _per_step(flops, steps), "scratch_mb": scratch_mb(compiled),
            # table only (not in the JSON line)
            "_raw_flops_per_env_step": _per_step(raw, steps), "_run_s": best, "_steps": steps,
            "_rollout_len": cfg.rollout_len, "_timed": timed}


def memory_skip(cfg, scenes, seeds: int = 1) -> dict | None:
    """{"skipped": why, "estimate_gb", "available_gb"} when the training preflight's
    estimate of one chunk (training/memory.py) times the seeds
    exceeds the machine's available memory, else None: such a row would end in XLA's
    RESOURCE_EXHAUSTED after minutes of compiling, so it is not run."""
    from orgnav_jax.training import memory
    need = sum(memory.chunk_memory_bytes(cfg, scenes).values()) * seeds
    have, where = memory.available_memory()
    if have is None or need <= have:
        return None
    why = (f"skipped: the memory estimate {memory.human(need)} exceeds the "
           f"{memory.human(have)} {where}")
    return {"skipped": why, "estimate_gb": round(need / 1e9, 1),
            "available_gb": round(have / 1e9, 1)}


def retime(row: dict, repeats: int) -> None:
    """Time a row's compiled chunk again (after a SAVN row, on a shared machine) and keep
    the best of all its runs."""
    best = min(row["_run_s"], row["_timed"](repeats))
    flops = row["flops_per_env_step"]
    row.update(_run_s=best, env_steps_per_s=round(row["_steps"] / best, 1),
               gflops_per_s=None if flops is None else round(
                   flops * row["_steps"] / best / 1e9, 2))


def time_savn_row(preset: str, model_name: str, num_envs: int, scenes, updates: int,
                  repeats: int, first_order: bool = False, trained: "Trained | None" = None,
                  segments: int | None = None, lstm_layers: int | None = None) -> dict:
    """SAVN training (training/savn.py) at the preset's (or the trained run's) widths:
    env-steps/s of the jitted chunk, counting the env steps the episodes really took
    (env_steps_real; a row whose episode ended idles, masked, to the next segment boundary,
    where it starts a new episode) and the row steps (num_envs x savn_segments x
    savn_steps per update) apart. One untimed chunk first, so that the timed chunks start
    with episodes running in the rows as in a run; every timed run starts from that runner.
    `trained`: start from its parameters (a SAVN run's {"nav", "ll"}, a plain run's network
    with a fresh learned loss), so that the episodes are as long as its agent's."""
    from orgnav_jax.training import savn
    over = dict(model=model_name, num_envs=num_envs, updates_per_chunk=updates, savn=True,
                savn_first_order=first_order)
    if segments:
        over["savn_segments"] = segments
    if lstm_layers:
        over["lstm_layers"] = lstm_layers
    cfg = row_config(preset, trained, **over)
    skip = memory_skip(cfg, scenes)
    if skip:
        return {"preset": preset, "model": f"{model_name}+savn" + ("-fo" if first_order else ""),
                "num_envs": num_envs, **skip}
    chunk, runner = savn_chunk_and_runner(cfg, scenes, trained)
    t0 = time.perf_counter()
    traced = chunk.trace(runner, scenes)
    lowered = traced.lower()
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    flops = scan_aware_flops(traced.jaxpr, _flops(lowered.cost_analysis()))
    runner, _ = jax.block_until_ready(compiled(runner, scenes))       # rows mid-episode
    best, metrics = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        _, m = jax.block_until_ready(compiled(runner, scenes))
        dt = time.perf_counter() - t0
        if dt < best:
            best, metrics = dt, m
    real = float(metrics["env_steps_real"])
    slots = cfg.updates_per_chunk * cfg.steps_per_update
    return {"preset": preset, "model": f"{model_name}+savn" + ("-fo" if first_order else ""),
            "num_envs": num_envs, "lstm_layers": cfg.lstm_layers,
            "savn_segments": cfg.savn_segments,
            "env_steps_per_s": round(real / best, 1),
            "slot_steps_per_s": round(slots / best, 1), "real_fraction": round(real / slots, 3),
            "flops_per_row_step": _per_step(flops, slots),
            "compile_s": round(compile_s, 2), "scratch_mb": scratch_mb(compiled),
            "mean_episode_steps": round(float(metrics["length"]) /
                                        max(float(metrics["episodes"]), 1.0), 2),
            "trained": trained.label if trained else None, "_run_s": best}


def savn_chunk_and_runner(cfg, scenes, trained: "Trained | None" = None):
    """A SAVN config's jitted chunk (savn.make_savn_chunk) and a runner to time it with:
    fresh, or with `trained`'s parameters (a SAVN run's {"nav", "ll"}, a plain run's
    network with a fresh learned loss) and rows started from them."""
    from orgnav_jax.training import savn
    model, learned = build_model(cfg, scenes), savn.build_learned_loss()
    optimizer = make_optimizer(cfg)
    runner = savn.init_savn_runner(cfg, model, learned, optimizer, scenes,
                                   jax.random.PRNGKey(cfg.seed))
    if trained is not None:
        params = {"nav": trained.nav, "ll": trained.ll or runner.params["ll"]}
        k_rows = jax.random.fold_in(runner.key, 1)
        runner = runner.replace(params=params, opt_state=optimizer.init(params),
                                rows=savn.init_rows(cfg, model, trained.nav, scenes, k_rows))
    return savn.make_savn_chunk(cfg, model, learned, optimizer), runner


def tiny_train_scenes():
    """The tiny preset's train split (built and cached once): the rooms every preset's
    row is timed on (bench_scenes swaps in the preset's feature widths)."""
    return load_or_build("tiny", progress=False).split_view("train")


@dataclasses.dataclass
class Trained:
    """A training run's best-on-val parameters (--params-from): its config, its network's
    parameters and, for a SAVN run, its learned loss's; scenes: its training rooms."""
    label: str
    cfg: object
    nav: object
    ll: object
    scenes: object


def load_trained(run_dir: str) -> Trained:
    from orgnav_jax.training import runs
    model, params, cfg = runs.load_run_model(run_dir, best=True)
    scenes = runs.scenes_for(cfg).split_view("train").to_device()
    nav, ll = (params["nav"], params["ll"]) if cfg.savn else (params, None)
    return Trained(Path(run_dir).name, cfg, nav, ll, scenes)


def matmul_peak_gflops(n: int = 2048, repeats: int = 8) -> float:
    """Best-of-`repeats` GFLOP/s of a jitted float32 (n x n) @ (n x n) matmul."""
    ka, kb = jax.random.split(jax.random.PRNGKey(0))
    a = jax.random.normal(ka, (n, n), jnp.float32)
    b = jax.random.normal(kb, (n, n), jnp.float32)
    mm = jax.jit(jnp.matmul).lower(a, b).compile()
    jax.block_until_ready(mm(a, b))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(mm(a, b))
        best = min(best, time.perf_counter() - t0)
    return 2 * n ** 3 / best / 1e9


# --------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", nargs="+", default=sorted(ENCODERS),
                    help=f"models to time (default: all of {sorted(ENCODERS)})")
    ap.add_argument("--presets", nargs="+", default=["small", "paper"],
                    help="training config presets (their widths; default small paper)")
    ap.add_argument("--num-envs", type=int, nargs="+", default=[16, 64, 256])
    ap.add_argument("--updates-per-chunk", type=int, default=2,
                    help="updates in the timed jitted chunk (default 2)")
    ap.add_argument("--rollout-len", type=int, default=None,
                    help="override the preset's rollout_len (default: the preset's)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per row; best kept")
    ap.add_argument("--devices", type=int, nargs="+", default=[1],
                    help="devices the env axis is sharded over (rows for each; on CPU "
                         "forced host devices)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[1],
                    help="seeds in one program (a vmapped population; rows for each)")
    ap.add_argument("--dtype", nargs="+", default=["float32"],
                    choices=["float32", "bfloat16"], help="compute dtypes (rows for each)")
    ap.add_argument("--matmul-repeats", type=int, default=8)
    ap.add_argument("--ratio-rounds", type=int, default=3,
                    help="rounds of timing each model's row and its Baseline row in turn "
                         "before their ratio (ratio_to_baseline; docs/vtnet.md)")
    ap.add_argument("--savn", choices=("none", "also", "first-order"), default="none",
                    help="also time SAVN training of each model (training/savn.py; "
                         "first-order: both MAML orders); env-steps/s counts the steps the "
                         "episodes really took (docs/savn.md)")
    ap.add_argument("--savn-segments", type=int, nargs="+", default=[0],
                    help="SAVN rows: segments per update (savn_segments; 0: the config's; "
                         "a row for each)")
    ap.add_argument("--params-from", nargs="+", default=[], metavar="RUN_DIR",
                    help="time from trained runs' best-on-val parameters instead of the "
                         "presets: each run's model, widths and training rooms (a plain "
                         "run: its network, SAVN's learned loss fresh; a SAVN run: both; "
                         "the base model's row gets its network), so that SAVN's episodes "
                         "are as long as a trained agent's (--models and --presets are "
                         "then not used)")
    ap.add_argument("--lstm-layers", type=int, default=None,
                    help="LSTM layers of the timed networks (default: the preset's, 2; "
                         "with --savn, the SAVN rows' (TABLE_ROWS['dsavn']: 1, as SAVN's "
                         "release), for the plain row too, so that ratio_to_base compares "
                         "one network; not with --params-from: a run's network is its own)")
    args = ap.parse_args()
    if args.lstm_layers is not None and (args.lstm_layers < 1 or args.params_from):
        ap.error("--lstm-layers must be >= 1, and is not used with --params-from")
    if args.lstm_layers is None and args.savn != "none" and not args.params_from:
        args.lstm_layers = TABLE_ROWS["dsavn"]["lstm_layers"]
    bad = sorted(set(args.models) - set(ENCODERS))
    if bad:
        ap.error(f"unknown model(s) {bad}: expected some of {sorted(ENCODERS)}")
    shape = dict(updates_per_chunk=args.updates_per_chunk,
                 **({"rollout_len": args.rollout_len} if args.rollout_len else {}))
    for p in args.presets:      # every row's config before any work (a traceback after)
        for n in args.num_envs:
            try:
                get_config(p, num_envs=n, **shape)
            except ValueError as e:
                ap.error(str(e))
    if min(args.num_envs) < 1 or args.updates_per_chunk < 1 or args.repeats < 1 \
            or min(args.devices) < 1 or min(args.seeds) < 1:
        ap.error("--num-envs, --updates-per-chunk, --repeats, --devices and --seeds must "
                 "be >= 1")
    if min(args.savn_segments) < 0:
        ap.error("--savn-segments must be >= 0 (0: the config's)")
    for run in args.params_from:
        if not (Path(run) / "config.json").is_file():
            ap.error(f"--params-from {run}: no config.json (not a training run directory)")
        try:
            saved = load_config(run)
            for n in args.num_envs:
                dataclasses.replace(saved, savn=False, num_envs=n, **shape).validate()
        except ValueError as e:
            ap.error(f"--params-from {run}: {e}")
    for d in args.devices:
        if any(n % d for n in args.num_envs):
            ap.error(f"--num-envs {args.num_envs} must divide by every --devices ({d})")
    if max(args.devices) > len(jax.local_devices()):
        ap.error(f"--devices {max(args.devices)}: {len(jax.local_devices())} "
                 f"{jax.default_backend()} devices")

    print(f"jax {jax.__version__} backend {jax.default_backend()} devices {jax.devices()}",
          flush=True)
    peak = matmul_peak_gflops(repeats=args.matmul_repeats)
    print(f"fp32 matmul peak (2048^3, best of {args.matmul_repeats}): {peak:.1f} GFLOP/s "
          "(measured again after the rows; the larger is kept)", flush=True)

    base = tiny_train_scenes()
    head = (f"{'preset':6} {'model':9} {'D':>2} {'S':>2} {'dtype':8} {'N':>4} {'T':>3} "
            f"{'steps':>6} {'compile s':>9} "
            f"{'run s':>7} {'env-steps/s':>11} {'MFLOP/step':>10} {'xla raw':>8} "
            f"{'GFLOP/s':>8} {'% peak':>6}")
    print(head + "\n" + "-" * len(head), flush=True)
    rows = []
    if args.params_from:          # (label, scenes, [(model, trained run)])
        sources = []
        for run in args.params_from:
            t = load_trained(run)
            sources.append((t.label, t.scenes, [(t.cfg.model, t)]))
    else:
        sources = [(preset, bench_scenes(base, preset), [(m, None) for m in args.models])
                   for preset in args.presets]
    for preset, scenes, models in sources:
        for model_name, trained in models:
            for n, d, seeds, dtype in [(n, d, s, t) for t in args.dtype
                                       for d in args.devices for s in args.seeds
                                       for n in args.num_envs]:
                r = time_row(preset, model_name, n, scenes, args.updates_per_chunk,
                             args.rollout_len, args.repeats, d, seeds, dtype, trained,
                             args.lstm_layers)
                rows.append(r)
                if "skipped" in r:
                    print(f"{preset:6} {model_name:9} {d:2d} {seeds:2d} {dtype:8} {n:4d} "
                          f"{r['skipped']}", flush=True)
                    continue
                print(f"{preset:6} {model_name:9} {d:2d} {seeds:2d} {dtype:8} {n:4d} "
                      f"{r['_rollout_len']:3d} "
                      f"{r['_steps']:6d} {r['compile_s']:9.2f} {r['_run_s']:7.3f} "
                      f"{r['env_steps_per_s']:11.1f} "
                      f"{_col(r['flops_per_env_step'], 10, 1e6)} "
                      f"{_col(r['_raw_flops_per_env_step'], 8, 1e6)} "
                      f"{_col(r['gflops_per_s'], 8)} "
                      f"{_col(r['gflops_per_s'], 6, peak / 100)}", flush=True)
                if args.savn != "none" and d == 1 and seeds == 1 and dtype == "float32":
                    savn_rows = [time_savn_row(preset, model_name, n, scenes,
                                               args.updates_per_chunk, args.repeats, fo,
                                               trained, u, args.lstm_layers)
                                 for fo in (False, True)[:1 + (args.savn == "first-order")]
                                 for u in args.savn_segments]
                    retime(r, args.repeats)      # the base model again: best of both
                    for sv in savn_rows:
                        if "skipped" in sv:
                            rows.append(sv)
                            print(f"{preset:6} {sv['model']:15} N={n:<4d} {sv['skipped']}",
                                  flush=True)
                            continue
                        sv["ratio_to_base"] = round(sv["env_steps_per_s"] /
                                                    r["env_steps_per_s"], 3)
                        rows.append(sv)
                        print(f"{preset:6} {sv['model']:15} N={n:<4d} U={sv['savn_segments']}"
                              f" compile {sv['compile_s']:.1f} s, run {sv['_run_s']:.3f} s: "
                              f"{sv['env_steps_per_s']:.0f} real env-steps/s "
                              f"({sv['ratio_to_base']:.2f} of {model_name}'s "
                              f"{r['env_steps_per_s']:.0f}, best of its runs before and "
                              f"after); {sv['slot_steps_per_s']:.0f} row steps/s, "
                              f"{sv['real_fraction']:.2f} of them real, "
                              f"{sv['mean_episode_steps']} steps per finished episode; "
                              f"{_col(sv['flops_per_row_step'], 0, 1e6).strip()} MFLOP per "
                              f"row step against {_col(r['flops_per_env_step'], 0, 1e6).strip()}"
                              f" per env step; XLA scratch {sv['scratch_mb']:.0f} MB against "
                              f"{r['scratch_mb']:.0f} MB)", flush=True)
    print("D: devices (env axis sharded); S: seeds in one program; steps: env-steps per "
          "chunk (all seeds); MFLOP/step: scan-aware count; xla raw: "
          "compiled.cost_analysis() / env-steps (scan bodies counted once; per device when "
          "sharded); % peak: of the matmul peak measured first")
    peak = max(peak, matmul_peak_gflops(repeats=args.matmul_repeats))
    print(f"fp32 matmul peak, best of before and after: {peak:.1f} GFLOP/s", flush=True)
    for r in add_baseline_ratios(rows, args.ratio_rounds):   # VTNet's target: >= 1/3
        print(f"{r['preset']:6} {r['model']:9} N={r['num_envs']:<4d} {r['dtype']}: "
              f"{r['ratio_to_baseline']:.3f} of the Baseline's env-steps/s", flush=True)
    results = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    print(json.dumps({"results": results, "matmul_peak_gflops": round(peak, 2)}))


def add_baseline_ratios(rows: list[dict], rounds: int = 0) -> list[dict]:
    """Set ratio_to_baseline on each plain (A2C) row of another model: its env-steps/s
    over the Baseline row of the same preset, N, devices, seeds and dtype timed in this
    run (docs/vtnet.md) -> those rows. First `rounds` rounds of timing the row and its
    Baseline row once each, in turn (retime: each keeps its best), so that a shared
    machine's load, which changes over minutes, weighs on both alike."""
    def key(r):
        return r["preset"], r["num_envs"], r.get("devices"), r.get("seeds"), r.get("dtype")
    plain = [r for r in rows if "devices" in r and "savn" not in r["model"]
             and "skipped" not in r]
    base = {key(r): r["env_steps_per_s"] for r in plain if r["model"] == "baseline"}
    out = []
    base_rows = {key(r): r for r in plain if r["model"] == "baseline"}
    for r in plain:
        if r["model"] != "baseline" and key(r) in base:
            for _ in range(rounds):     # rows that keep their compiled chunk (_timed)
                for row in (base_rows[key(r)], r):
                    if "_timed" in row:
                        retime(row, 1)
                base[key(r)] = base_rows[key(r)]["env_steps_per_s"]
            r["ratio_to_baseline"] = round(r["env_steps_per_s"] / base[key(r)], 3)
            out.append(r)
    return out


if __name__ == "__main__":
    main()
