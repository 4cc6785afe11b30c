"""Benchmark: the env step of this checkout against an older commit, side by side.

    python benchmarks/env_versions.py 4ca89d4                  # 1, 1,024 and 8,192 envs
    python benchmarks/env_versions.py 4ca89d4 --rounds 3 --num-envs 1024

Runs this checkout's benchmarks/env_throughput.py (random actions with auto-reset, `small`
scenes, every output of the step consumed) on the package of a git worktree of OLD and on
this checkout's in turn, --rounds times each (old, new, old,
new, ...), so that a machine's changing load weighs on both alike, and keeps each
version's best M env-steps/s per size. Prints a table with new / old per size, then one
JSON object as the last line. The worktree is removed at the end.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

TOP = Path(__file__).resolve().parents[1]


def run_version(tree: Path, num_envs: list[int], repeats: int) -> dict[int, float]:
    """This checkout's env_throughput.py on `tree`'s package (on PYTHONPATH): the same
    measurement of both versions -> {num_envs: steps/s}."""
    cmd = [sys.executable, str(TOP / "benchmarks" / "env_throughput.py"), "--num-envs",
           *map(str, num_envs), "--repeats", str(repeats)]
    proc = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)},
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"env_throughput.py of {tree} failed:\n{proc.stderr[-2000:]}")
    rows = json.loads(proc.stdout.strip().splitlines()[-1])["rows"]
    return {r["num_envs"]: r["steps_per_s"] for r in rows}


def needed_modules() -> list[str]:
    """The package modules env_throughput.py imports ('orgnav_jax/env.py', ...)."""
    text = (TOP / "benchmarks" / "env_throughput.py").read_text()
    names = re.findall(r"^from (orgnav_jax(?:\.\w+)*) import (\w+(?:, \w+)*)", text, re.M)
    out = []
    for module, items in names:
        path = module.replace(".", "/")
        out += [f"{path}/{item}" for item in items.split(", ")] if module == "orgnav_jax" \
            else [path]
    return out


def in_commit(commit: str, module: str) -> bool:
    """Whether `commit` holds `module` (a path without .py) as a file or a package."""
    return any(subprocess.run(["git", "cat-file", "-e", f"{commit}:{module}{suffix}"],
                              cwd=TOP, capture_output=True).returncode == 0
               for suffix in (".py", "/__init__.py"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("old", help="the commit to compare with (e.g. 4ca89d4)")
    ap.add_argument("--num-envs", type=int, nargs="+", default=[1, 1024, 8192])
    ap.add_argument("--rounds", type=int, default=2, help="runs of each version, in turn")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per size per run")
    args = ap.parse_args()
    if args.rounds < 1 or args.repeats < 1 or min(args.num_envs) < 1:
        ap.error("--rounds, --repeats and --num-envs must be >= 1")
    # a commit (not a tree or a blob: `git worktree add` failed with a traceback) whose
    # package has every module env_throughput.py imports (an older one ran it to an
    # ImportError in the worktree), checked before the worktree is made
    commit = subprocess.run(["git", "rev-parse", "--verify", "--quiet", "--short",
                             f"{args.old}^{{commit}}"], cwd=TOP, capture_output=True,
                            text=True)
    if commit.returncode != 0:
        kind = subprocess.run(["git", "cat-file", "-t", args.old], cwd=TOP,
                              capture_output=True, text=True).stdout.strip()
        ap.error(f"{args.old!r} {'is a ' + kind if kind else 'names nothing'} in {TOP}, "
                 "expected a commit")
    missing = [m.replace("/", ".") for m in needed_modules() if not in_commit(args.old, m)]
    if missing:
        ap.error(f"commit {commit.stdout.strip()} has no module {', '.join(missing)}: "
                 "benchmarks/env_throughput.py needs them (the env and its scenes); expected "
                 "a commit with the env")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=TOP,
                          capture_output=True, text=True).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="orgnav-env-versions-") as work:
        old_tree = Path(work) / "old"
        subprocess.run(["git", "worktree", "add", "-f", "-q", str(old_tree), args.old],
                       cwd=TOP, check=True)
        best = {"old": {}, "new": {}}
        try:
            for k in range(args.rounds):
                for name, tree in (("old", old_tree), ("new", TOP)):
                    got = run_version(tree, args.num_envs, args.repeats)
                    for n, sps in got.items():
                        best[name][n] = max(best[name].get(n, 0.0), sps)
                    print(f"round {k + 1} {name}: " + ", ".join(
                        f"{n}: {sps / 1e6:.3f} M/s" for n, sps in got.items()), flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(old_tree)], cwd=TOP)
    rows = [{"num_envs": n, "old_steps_per_s": round(best["old"][n], 1),
             "new_steps_per_s": round(best["new"][n], 1),
             "new_over_old": round(best["new"][n] / best["old"][n], 3)} for n in args.num_envs]
    print(f"{'num_envs':>8} {args.old + ' M/s':>14} {head + ' M/s':>14} {'new/old':>8}")
    for r in rows:
        print(f"{r['num_envs']:8d} {r['old_steps_per_s'] / 1e6:14.3f} "
              f"{r['new_steps_per_s'] / 1e6:14.3f} {r['new_over_old']:8.3f}")
    print(json.dumps({"benchmark": "env_versions", "old": commit.stdout.strip(), "new": head,
                      "cpu_count": os.cpu_count(), "rounds": args.rounds, "rows": rows}))


if __name__ == "__main__":
    main()
