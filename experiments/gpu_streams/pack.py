"""Pack the runs of run.sh's streams (/tmp/g/out*/runs) into OUT_DIR, for a transfer of at
most 8 files of 16 MB (63 MB in all):

- small.tgz: every run's small files (config, metrics, test results, provenance; no
  checkpoints, TensorBoard logs or episode caches), the streams' logs, tables and the
  sweeps' records (OUT*/*.json, *.md);
- best_ROW.tar: the best-on-val checkpoints of a finished row that a TPN row of a stream's
  spec builds on (ROW+... in its rows), so its TPN rows can run elsewhere;
- part_runs.tar: what lets runs go on elsewhere, most advanced first, as many as fit: the
  latest and best checkpoints of a run stopped short of its budget (a row's or a command
  stream's), the best checkpoint of a row's run trained but not tested.

An archive over 16 MB is split into NAME.0, NAME.1, ... (`cat NAME.* | tar x`).

usage: python experiments/gpu_streams/pack.py OUT_DIR
"""
from __future__ import annotations

import io
import json
import sys
import tarfile
from pathlib import Path

from orgnav_jax.training.run_dir import saved_steps

STREAMS = Path("/tmp/g")
FILE_LIMIT, TOTAL_LIMIT, MAX_FILES = 15_900_000, 63_000_000, 8
BIG = {"checkpoints", "best", "tb"}


def newest(run: Path, sub: str) -> list[tuple[Path, str]]:
    """[(the newest step directory of RUN/SUB, its name in the archive)], [] if none."""
    steps = saved_steps(run, sub)
    if not steps:
        return []
    return [(run / sub / str(steps[-1]), f"runs/{run.name}/{sub}/{steps[-1]}")]


def tar_bytes(items: list[tuple[Path, str]]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as t:
        for path, arcname in items:
            t.add(path, arcname)
    return buf.getvalue()


def env_steps(run: Path) -> int:
    """The last metrics record's env_steps (0: none yet)."""
    try:
        return json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])["env_steps"]
    except (OSError, IndexError, KeyError, ValueError):
        return 0


def budget(run: Path) -> int:
    """The run's total_env_steps (config.json; 0 when unreadable)."""
    try:
        return int(json.loads((run / "config.json").read_text())["total_env_steps"])
    except (OSError, KeyError, ValueError):
        return 0


def main(out: Path) -> None:
    runs = sorted(r for o in STREAMS.glob("out*") for r in (o / "runs").glob("*")
                  if r.is_dir())
    with tarfile.open(out / "small.tgz", "w:gz") as t:
        for run in runs:
            for f in run.rglob("*"):
                rel = f.relative_to(run)
                small = not set(rel.parts) & BIG and not f.name.startswith(("episodes-", "."))
                if f.is_file() and small:
                    t.add(f, f"runs/{run.name}/{rel}")
        for f in [*STREAMS.glob("log*.txt"), *STREAMS.glob("out*/*.md"),
                  *STREAMS.glob("out*/*.json")]:      # tables, results, sweeps' records
            t.add(f, f"meta/{f.parent.name}-{f.name}")
    files, total = 2, (out / "small.tgz").stat().st_size      # small.tgz and log.txt

    def write(name: str, data: bytes) -> None:
        nonlocal files, total
        parts = [data[i:i + FILE_LIMIT] for i in range(0, len(data), FILE_LIMIT)]
        if files + len(parts) > MAX_FILES or total + len(data) > TOTAL_LIMIT:
            print(f"{name}: {len(data):,} bytes do not fit; left out")
            return
        for i, part in enumerate(parts):
            (out / (name if len(parts) == 1 else f"{name}.{i}")).write_bytes(part)
        files, total = files + len(parts), total + len(data)
        print(f"{name}: {len(data):,} bytes in {len(parts)} file(s)")

    by_row: dict[str, list[Path]] = {}
    for run in runs:
        row, _, seed = run.name.rpartition("-s")
        if seed.isdigit() and "pretrain" not in row:
            by_row.setdefault(row, []).append(run)
    finished = {row for row, rs in by_row.items()
                if all((r / "test_results.json").exists() for r in rs)}
    specs = [json.loads(p.read_text()) for p in STREAMS.glob("spec*.json")]
    bases = [row for spec in specs for row in dict.fromkeys(
        r.partition("+")[0] for r in spec["rows"] if "+" in r)]
    for row in bases:
        if row in finished:
            write(f"best_{row}.tar",
                  tar_bytes([x for r in by_row[row] for x in newest(r, "best")]))
    # runs to go on elsewhere, most advanced first, as many as fit: a row's run trained but
    # not tested (its best checkpoint), or any run stopped short of its budget (a row's or
    # a command stream's: its latest and best checkpoints)
    rows = {r for spec in specs for r in spec["rows"]}
    todo = []
    for run in runs:
        if "pretrain" in run.name or (run / "test_results.json").exists():
            continue
        if env_steps(run) >= budget(run):
            if run.name.rpartition("-s")[0] in rows:
                todo.append((float("inf"), run, ("best",)))
        elif newest(run, "checkpoints"):
            todo.append((env_steps(run), run, ("checkpoints", "best")))
    items, room = [], TOTAL_LIMIT - total
    for _, run, subs in sorted(todo, key=lambda t: -t[0]):
        these = [x for sub in subs for x in newest(run, sub)]
        size = sum(f.stat().st_size for path, _ in these for f in path.rglob("*")
                   if f.is_file())
        if size + 100_000 * len(these) <= room:             # tar headers, generously
            items, room = items + these, room - size - 100_000 * len(these)
            print(f"{run.name}: {', '.join(subs)} packed ({env_steps(run):,} env steps)")
        else:
            print(f"{run.name}: {', '.join(subs)} do not fit; left out")
    if items:
        write("part_runs.tar", tar_bytes(items))
    print(f"{files} files, {total:,} bytes")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
