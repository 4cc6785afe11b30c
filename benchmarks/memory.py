"""Benchmark: peak memory (RSS) of real-size scene sets, next to their feature bytes.

    python benchmarks/memory.py                       # 10, 20 and 40 rooms of `large`
    python benchmarks/memory.py --rooms 10 --import   # also export + import 10 rooms

For each room count N it builds N rooms of the `large` preset (AI2-THOR room sizes,
paper widths 7x7x512 and 22x512, raw float16 features, the val + test floor plans), then
measures, each step in a child process of its own (its peak RSS is getrusage of that
child alone):
    import      export to the authors' offline format, then `scenes import` (--import)
    load        scenes.load(mmap=True) + the test split on the device
    eval-expert evaluate the expert on the test split (250 episodes per room type)
    eval-model  evaluate a paper-width Baseline (initial weights) on the test split
and once, for a 20-room train split (5 train + 1 val room per type):
    train-chunk one jitted training chunk of a paper-width Baseline + its val evaluation
Targets (issue 14): eval <= 1.5 x feature bytes + 2 GB; the training chunk fits 16 GB.
Prints a table, then one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

GB = 1e9


def _peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024   # Linux: KiB


def _feature_bytes(set_dir: str) -> int:
    meta = json.loads((Path(set_dir) / "meta.json").read_text())
    total = 0
    for name in ("global_feat", "appearance"):
        f = meta["fields"][name]
        n = 1
        for d in f["shape"]:
            n *= d
        total += n * {"float16": 2, "int8": 1, "float32": 4}[f["dtype"]]
    return total


# ---------------------------------------------------------------- child steps
def child_build(out: str, rooms: int, train_rooms: int) -> dict:
    from orgnav_jax import scenes
    t0 = time.perf_counter()
    if train_rooms:
        scenes.build_to("large", 0, out, rooms_per_type=(train_rooms, 1, 0))
    else:
        scenes.build_to("large", 0, out, num_rooms=rooms)
    s = scenes.load(out, mmap=True)
    return {"seconds": time.perf_counter() - t0, "states": int(s.num_states),
            "rooms": int(s.num_scenes)}


def child_import(src: str, work: str) -> dict:
    from orgnav_jax import scenes
    from orgnav_jax.scenes.offline import export_offline, import_to
    offline, out = Path(work) / "offline", Path(work) / "imported"
    export_offline(scenes.load(src, mmap=True), offline, hdf5_dtype="float16")
    t0 = time.perf_counter()
    import_to(offline, out)
    seconds = time.perf_counter() - t0
    shutil.rmtree(offline)
    shutil.rmtree(out)
    return {"seconds": seconds}


def child_load(src: str) -> dict:
    import jax
    from orgnav_jax import scenes
    t0 = time.perf_counter()
    test = scenes.load(src, mmap=True).split_view("test").to_device()
    jax.block_until_ready(test.global_feat)
    return {"seconds": time.perf_counter() - t0}


def child_eval_expert(src: str, work: str) -> dict:
    from orgnav_jax import api
    t0 = time.perf_counter()
    res = api.evaluate_policy("expert", split="test", scenes_dir=src, progress=False,
                              out=Path(work) / "expert.json")
    return {"seconds": time.perf_counter() - t0, "episodes": res["overall"]["episodes"],
            "success": res["overall"]["success"]}


def child_eval_model(src: str, per_room_type: int) -> dict:
    import jax
    from orgnav_jax import env, evaluation, scenes
    from orgnav_jax.episodes import sample_episodes
    from orgnav_jax.models import build_model, init_params
    from orgnav_jax.training.config import get_config
    from orgnav_jax.training.runs import model_policy
    cfg = get_config("paper", scenes_dir=src)
    test = scenes.load(src, mmap=True).split_view("test").to_device()
    model = build_model(cfg, test)
    params = init_params(model, jax.random.PRNGKey(0), test)
    episodes = sample_episodes(test, per_room_type, seed=0, split="test")
    t0 = time.perf_counter()
    res = evaluation.evaluate(model_policy(model), params, test, episodes,
                              env.EnvParams.evaluation())
    return {"seconds": time.perf_counter() - t0, "episodes": res["overall"]["episodes"]}


def child_train_chunk(src: str, work: str) -> dict:
    from orgnav_jax import api
    from orgnav_jax.training.config import get_config
    cfg = get_config("paper", scenes_dir=src, run_dir=str(Path(work) / "run"),
                     total_env_steps=64 * 16 * 25, updates_per_chunk=25,
                     eval_episodes_per_room_type=10)
    summary = api.train(cfg, progress=False)
    return {"seconds": summary["wall_s"], "env_steps": summary["env_steps"],
            "compile_plus_first_chunk_s": summary["compile_plus_first_chunk_s"]}


CHILDREN = {"build": child_build, "import": child_import, "load": child_load,
            "eval-expert": child_eval_expert, "eval-model": child_eval_model,
            "train-chunk": child_train_chunk}


def _run(step: str, *args) -> dict:
    """This script as a child doing `step` -> its JSON plus wall seconds and peak RSS."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", step, *map(str, args)],
                          stdout=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"child {step} failed with exit code {proc.returncode}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rooms", type=int, nargs="+", default=[10, 20, 40])
    ap.add_argument("--import", dest="with_import", action="store_true",
                    help="also export + import each set (writes as much again to disk)")
    ap.add_argument("--model-episodes", type=int, default=25,
                    help="episodes per room type of the paper-width model evaluation")
    ap.add_argument("--no-train", action="store_true", help="skip the training chunk")
    ap.add_argument("--workdir", default=None, help="where the sets go (deleted after)")
    ap.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        step, *rest = args.child
        fn = CHILDREN[step]
        kinds = {"build": (str, int, int), "eval-model": (str, int)}.get(step)
        rest = [k(v) for k, v in zip(kinds, rest)] if kinds else rest
        out = fn(*rest)
        out["peak_rss_gb"] = round(_peak_rss_bytes() / GB, 2)
        print(json.dumps(out))
        return
    work = Path(args.workdir or tempfile.mkdtemp(prefix="orgnav-memory-"))
    work.mkdir(parents=True, exist_ok=True)
    rows, table = [], []
    try:
        for n in args.rooms:
            src = str(work / f"large-{n}")
            built = _run("build", src, n, 0)
            feat = _feature_bytes(src)
            row = {"rooms": n, "states": built["states"], "feature_gb": round(feat / GB, 2),
                   "build": built}
            if args.with_import:
                row["import"] = _run("import", src, str(work))
            row["load"] = _run("load", src)
            row["eval-expert"] = _run("eval-expert", src, str(work))
            row["eval-model"] = _run("eval-model", src, args.model_episodes)
            target = 1.5 * feat / GB + 2
            row["eval_target_gb"] = round(target, 2)
            rows.append(row)
            shutil.rmtree(src)
            print(json.dumps(row), flush=True)
        if not args.no_train:
            src = str(work / "train-20")
            built = _run("build", src, 0, 5)
            train = _run("train-chunk", src, str(work))
            rows.append({"rooms": built["rooms"], "states": built["states"],
                         "feature_gb": round(_feature_bytes(src) / GB, 2),
                         "train-chunk": train})
            shutil.rmtree(src)
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)
    print(f"\npeak RSS in GB ({platform.node()}, {platform.processor() or 'cpu'}):")
    print("| rooms | states | features GB | import | load | eval expert | eval model "
          "| target (1.5 x feat + 2) | train chunk |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        cell = lambda k: f"{r[k]['peak_rss_gb']:.2f}" if k in r else "-"
        table.append(f"| {r['rooms']} | {r['states']:,} | {r['feature_gb']:.2f} | "
                     f"{cell('import')} | {cell('load')} | {cell('eval-expert')} | "
                     f"{cell('eval-model')} | {r.get('eval_target_gb', '-')} | "
                     f"{cell('train-chunk')} |")
    print("\n".join(table))
    print(json.dumps({"rows": rows}))


if __name__ == "__main__":
    main()
