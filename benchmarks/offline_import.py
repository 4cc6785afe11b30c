"""Benchmark: export the `paper` preset (G = d = 512) to the authors' offline format and
import it back, timing both and measuring the importer's peak memory.

    python benchmarks/offline_import.py                    # 1 train room per type (4 rooms)
    python benchmarks/offline_import.py --rooms 20 5 5     # the whole preset (~50 GB of hdf5)

Export and import each run in a child process, so that the import's peak RSS
(getrusage of that child) counts nothing but the import (and its save). Prints a table,
then one JSON object as the last line.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _child_export(out: str, rooms: list[int], seed: int) -> None:
    from orgnav_jax import scenes
    from orgnav_jax.scenes.offline import export_offline
    t0 = time.perf_counter()
    s = scenes.build("paper", seed, rooms_per_type=tuple(rooms))
    build_s = time.perf_counter() - t0
    report = export_offline(s, out)
    print(json.dumps(dict(report, build_s=round(build_s, 2))))


def _child_import(src: str, out: str) -> None:
    import numpy as np

    from orgnav_jax import scenes
    from orgnav_jax.scenes.offline import import_offline
    t0 = time.perf_counter()
    s, report = import_offline(src)
    import_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    scenes.save(s, out)
    save_s = time.perf_counter() - t0
    arrays = [getattr(s, f) for f in ("next_state", "pose", "visible", "dist",
                                      "expert_action", "det_box", "det_conf", "appearance",
                                      "global_feat", "present", "targets")]
    print(json.dumps({"import_s": round(import_s, 2), "save_s": round(save_s, 2),
                      "phases": report["seconds"], "states": report["states"],
                      "max_states": report["max_states"], "scenes": report["num_scenes"],
                      "optimal_action": report["optimal_action"],
                      "output_mb": round(sum(np.asarray(a).nbytes for a in arrays) / 2**20, 1)}))


def _run(args: list[str]) -> tuple[dict, float, float]:
    """Run this script as a child -> (its JSON line, wall seconds, peak RSS MiB)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, __file__, *args], stdout=subprocess.PIPE, text=True)
    out = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise SystemExit(f"child {args[0]} failed with exit code {proc.returncode}")
    wall = time.perf_counter() - t0
    return json.loads(out.strip().splitlines()[-1]), wall, usage.ru_maxrss / 1024  # KiB -> MiB


def _dir_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child-export":
        return _child_export(sys.argv[2], [int(v) for v in sys.argv[3:6]], int(sys.argv[6]))
    if len(sys.argv) > 1 and sys.argv[1] == "--child-import":
        return _child_import(sys.argv[2], sys.argv[3])
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rooms", nargs=3, type=int, default=[1, 0, 0],
                    metavar=("TRAIN", "VAL", "TEST"), help="paper-preset rooms per type")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", help="keep the exported and imported data here "
                    "(default: a temporary directory, removed)")
    args = ap.parse_args()

    work = Path(args.workdir or tempfile.mkdtemp(prefix="offline_bench."))
    work.mkdir(parents=True, exist_ok=True)
    try:
        exp, _, exp_rss = _run(["--child-export", str(work / "offline"),
                                       *map(str, args.rooms), str(args.seed)])
        offline_mb = _dir_mb(work / "offline")
        imp, imp_wall, imp_rss = _run(["--child-import", str(work / "offline"),
                                       str(work / "sceneset")])
        sceneset_mb = _dir_mb(work / "sceneset")
    finally:
        if not args.workdir:
            shutil.rmtree(work, ignore_errors=True)

    row = {
        "preset": "paper", "rooms_per_type": args.rooms, "scenes": imp["scenes"],
        "states": imp["states"], "max_states": imp["max_states"],
        "build_s": exp["build_s"], "export_s": exp["seconds"],
        "export_peak_rss_mb": round(exp_rss),
        "offline_mb": round(offline_mb, 1), "import_s": imp["import_s"],
        "import_phases_s": imp["phases"],
        "import_states_per_s": round(imp["states"] / imp["import_s"]),
        "import_hdf5_mb_per_s": round(offline_mb / imp["import_s"], 1),
        "save_s": imp["save_s"], "import_child_wall_s": round(imp_wall, 1),
        "import_peak_rss_mb": round(imp_rss), "output_mb": imp["output_mb"],
        "sceneset_disk_mb": round(sceneset_mb, 1), "optimal_action": imp["optimal_action"],
    }
    head = ("scenes", "states", "offline_mb", "export_s", "import_s", "import_states_per_s",
            "import_hdf5_mb_per_s", "output_mb", "import_peak_rss_mb")
    print(" | ".join(f"{h:>20}" for h in head))
    print(" | ".join(f"{row[h]!s:>20}" for h in head))
    print(json.dumps({"benchmark": "offline_import", "cpu_count": os.cpu_count(),
                      "machine": platform.machine(), "results": [row]}))


if __name__ == "__main__":
    main()
