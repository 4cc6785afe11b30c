"""Benchmark: where a SAVN training update spends its time, op by op (XLA's CPU trace).

    python benchmarks/savn_profile.py --params-from RUN_DIR         # a trained run's network
    python benchmarks/savn_profile.py --preset dsavn --top 40       # fresh parameters

Compiles one SAVN update (training/savn.py: make_savn_chunk, 1 update per chunk, 64 rows
by default), runs it twice untimed, then `--chunks` times under `jax.profiler.trace` with
XLA's per-op trace events on (XLA_FLAGS=--xla_cpu_enable_xprof_traceme=true, set by this
script before jax is imported). Each event is an HLO op of the compiled program; its
`op_name` metadata (from the compiled HLO text) names the JAX code it came from. Prints,
in ms per update (op time summed; ops on the two threads overlap, so the sum can exceed
the wall time):

* by differentiation order: (transposes, jvps) in the op's name path. (0, 1): the outer
  forward (acting, the loss); (0, 2): the inner pass's forward; (1, 2): the inner
  gradient and the outer backward of the forward; (2, 2): the second-order terms;
* by op kind (dot: XLA's own dot, e.g. the per-row batched products; ynn_fusion: a
  YNNPACK fusion, e.g. the shared matmuls; copy: layout copies and buffer initialisation);
* the top ops by op name, shape and kind.

The machine may be shared: compare only numbers from one run, or run it alone.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

if __name__ == "__main__":               # before jax is imported (not when a test imports it)
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                               " --xla_cpu_enable_xprof_traceme=true").strip()
sys.path.insert(0, str(Path(__file__).resolve().parent))

import jax  # noqa: E402

from orgnav_jax.training.config import get_config  # noqa: E402


def op_metadata(hlo_text: str) -> dict[str, tuple[str, str]]:
    """{HLO op name: (result shape, op_name metadata)} from a compiled program's text."""
    meta = {}
    for line in hlo_text.splitlines():
        m = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = (\S+) ", line)
        if m:
            op = re.search(r'op_name="([^"]*)"', line)
            meta[m.group(1)] = (m.group(2).split("{")[0], op.group(1) if op else "")
    return meta


def op_times(trace_dir: str, meta: dict) -> dict[str, tuple[float, int]]:
    """{HLO op name: (total microseconds, events)} of the trace's events that are ops of
    `meta`."""
    path = glob.glob(f"{trace_dir}/**/*.trace.json.gz", recursive=True)
    if not path:
        raise SystemExit(f"savn_profile: no trace file under {trace_dir}")
    events = json.load(gzip.open(path[0]))
    events = events["traceEvents"] if isinstance(events, dict) else events
    total, count = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and e.get("name") in meta:
            total[e["name"]] += e.get("dur", 0)
            count[e["name"]] += 1
    return {name: (total[name], count[name]) for name in total}


def short(op_name: str) -> str:
    """An op_name without the chunk's loop wrappers and numeric suffixes."""
    parts = [p for p in op_name.split("/") if p not in ("jit(chunk)", "while", "body",
                                                       "closed_call")]
    return re.sub(r"\.\d+", "", "/".join(parts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--params-from", help="a run directory: its network and best-on-val "
                                          "parameters (as train_throughput.py)")
    ap.add_argument("--preset", default="dsavn", help="without --params-from (default dsavn)")
    ap.add_argument("--num-envs", type=int, default=64)
    ap.add_argument("--chunks", type=int, default=3, help="profiled updates (default 3)")
    ap.add_argument("--top", type=int, default=25, help="top ops printed (default 25)")
    args = ap.parse_args()

    import train_throughput as tt
    if args.params_from:
        trained = tt.load_trained(args.params_from)
        cfg, scenes = trained.cfg, trained.scenes
    else:
        trained = None
        cfg = get_config(args.preset)
        scenes = tt.bench_scenes(tt.tiny_train_scenes(), args.preset)
    cfg = dataclasses.replace(cfg, savn=True, num_envs=args.num_envs,
                              updates_per_chunk=1).validate()
    chunk, runner = tt.savn_chunk_and_runner(cfg, scenes, trained)
    t0 = time.perf_counter()
    compiled = chunk.lower(runner, scenes).compile()
    print(f"compile {time.perf_counter() - t0:.1f} s", flush=True)
    for _ in range(2):                                 # rows mid-episode, caches warm
        runner, _ = jax.block_until_ready(compiled(runner, scenes))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(args.chunks):
                jax.block_until_ready(compiled(runner, scenes))
        wall = (time.perf_counter() - t0) / args.chunks
        meta = op_metadata(compiled.as_text())
        times = op_times(tmp, meta)
    per = {k: us / 1e3 / args.chunks for k, (us, _) in times.items()}   # ms per update
    print(f"{cfg.num_envs} rows x {cfg.savn_segments} segments x {cfg.savn_steps} steps; "
          f"wall {wall * 1e3:.0f} ms per update (traced), op time {sum(per.values()):.0f} ms")
    order, kind, by_op, runs = (collections.Counter() for _ in range(4))
    for name, ms in per.items():
        shape, op = meta[name]
        order[(op.count("transpose("), op.count("jvp("))] += ms
        kind[re.sub(r"\.\d+$", "", name)] += ms
        key = (short(op)[-90:], shape, re.sub(r"\.\d+$", "", name))
        by_op[key] += ms
        runs[key] += times[name][1] / args.chunks
    print("\nby (transposes, jvps) in the op's path, ms per update:")
    for k, ms in order.most_common():
        print(f"  {str(k):8s} {ms:7.1f}")
    print("\nby op kind, ms per update:")
    for k, ms in kind.most_common(12):
        print(f"  {k:40s} {ms:7.1f}")
    print(f"\ntop {args.top} ops (op_name, shape, kind): ms and executions per update")
    for key, ms in by_op.most_common(args.top):
        op, shape, k = key
        print(f"  {ms:6.1f} {runs[key]:5.0f}  {k:22s} {shape:22s} {op}")


if __name__ == "__main__":
    main()
