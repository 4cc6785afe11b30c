"""Where a table's files lie (experiments/run_table.py makes them; docs/results.md):

    OUT/spec.json                      the table's definition (spec.py)
    OUT/results.json, table.md, claims.md, provenance.md, curves.png    generated
    OUT/convergence.md                 generated for a spec with "converged": true
    OUT/runs/ROW-sS/                   row ROW's run of seed S: config.json, metrics.jsonl,
                                       test_results.json, provenance.json
    OUT/runs/BASE-sS/tpn/              the TPN (stage 2) of BASE's run; a row
                                       BASE+VARIANT@LR's results in test_VARIANT@LR.json
    OUT/runs/ROW-pretrain-sS/          a PRETRAIN_ROWS row's pre-training of seed S
"""

from __future__ import annotations

from pathlib import Path

from orgnav_jax.errors import read_json
from orgnav_jax.tables.rows import Row

# the files run_table.py (re)writes in OUT
TABLE_FILES = ("spec.json", "results.json", "table.md", "claims.md", "provenance.md",
               "curves.png", "convergence.md")


def local_path(path: Path) -> Path:
    """`path` relative to the working directory when it lies under it, else as given: the
    run directory an experiment script gives the trainer, so that the config.json it
    records names no one machine's checkout."""
    return path.relative_to(Path.cwd()) if path.is_relative_to(Path.cwd()) else path


def run_dir(out: Path, row: str | Row, seed: int | str) -> Path:
    """OUT/runs/BASE-sS: the run of a row (of a TPN row: its base row's run)."""
    row = row if isinstance(row, Row) else Row.of(row)
    return out / "runs" / f"{row.base}-s{seed}"


def results_path(out: Path, row: str | Row, seed: int | str) -> Path:
    """Where a row's test results for one seed live: OUT/runs/ROW-sS/test_results.json, or
    for BASE+VARIANT[@LR] OUT/runs/BASE-sS/tpn/test_VARIANT[@LR].json."""
    row = row if isinstance(row, Row) else Row.of(row)
    base = run_dir(out, row, seed)
    return base / "tpn" / f"test_{row.tpn_tag}.json" if row.is_tpn else \
        base / "test_results.json"


def existing_results(out: Path, row: str | Row, seed: int | str) -> Path | None:
    """results_path(out, row, seed) if that file exists, None if it does not; a path
    that cannot be looked at (a symbolic link loop, a link that leads nowhere, no
    permission) is a ValueError naming it, never taken as "not run yet" (a run of the
    table would otherwise drop out of it without a word)."""
    path = results_path(out, row, seed)
    try:
        path.stat()
        return path
    except FileNotFoundError:
        pass
    except OSError as err:
        raise ValueError(f"{path}: cannot be read ({err.strerror}; a symbolic link loop?)"
                         ) from None
    p = path
    while p != out and p != p.parent:         # absent, unless a link on the way is broken
        if p.is_symlink() and not p.exists():
            raise ValueError(f"{p}: a symbolic link that leads nowhere")
        p = p.parent
    return None


def pretrain_dir(out: Path, base: str, seed: int | str) -> Path:
    """Where a PRETRAIN_ROWS row's seed is pre-trained: OUT/runs/ROW-pretrain-sS (the
    directory `--preset vtnet --seeds` uses for RUN_DIR = OUT/runs/ROW)."""
    return out / "runs" / f"{base}-pretrain-s{seed}"


def table_run_dirs(out: Path, spec: dict) -> list[Path]:
    """The run directories a table's rows read, in the spec's order, each once: a row's
    run (a TPN row's: its base run's tpn/) and, for a pre-trained row, the seed's
    pre-training before it."""
    dirs: list[Path] = []
    for name in spec["rows"]:
        row = Row.of(name)
        for seed in spec["seeds"]:
            found = [results_path(out, row, seed).parent]
            if row.pretrains:
                found.insert(0, pretrain_dir(out, row.base, seed))
            dirs += [d for d in found if d not in dirs]
    return dirs


def check_out(out: Path, spec_path: str | None) -> None:
    """--out must be new, or a table run_table.py made (it holds runs/ or a results.json
    of rows and seeds), or hold none of the table files it rewrites (TABLE_FILES): a
    folder with the user's own spec.json or table.md is refused before anything is
    written; so is a spec that lies at OUT/spec.json, which the table would replace.
    Other files in --out are never touched."""
    if not out.exists():
        return
    if not out.is_dir():
        raise ValueError(f"--out {out}: not a directory")
    if spec_path is not None and (out / "spec.json").exists() and \
            Path(spec_path).resolve() == (out / "spec.json").resolve():
        raise ValueError(f"--spec {spec_path}: lies at OUT/spec.json, which the table "
                         "rewrites: keep the spec outside its output directory")
    saved = out / "results.json"
    if saved.exists():
        doc = read_json(saved, "a results JSON")
        if not (isinstance(doc, dict) and all(
                isinstance(v, dict) and all(isinstance(r, dict) for r in v.values())
                for v in doc.values())):
            raise ValueError(f"--out {out}: its results.json is not a table's "
                             "(results[row][seed] = metrics): not overwritten; choose a "
                             "new directory")
        return
    if (out / "runs").is_dir():
        return
    present = [name for name in TABLE_FILES if (out / name).exists() or
               (out / name).is_symlink()]
    if present:
        raise ValueError(f"--out {out}: holds {', '.join(present)} that run_table.py did "
                         "not write (no runs/, no results.json): choose a new directory "
                         "(nothing was written)")
