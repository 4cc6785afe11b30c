"""A table directory's generated files, made from its runs' files and nothing else:
results.json, table.md (table.py), claims.md (claims.py), provenance.md (provenance.py)
and, for a spec with "converged": true, convergence.md (convergence_page.py); written
together, or checked (`claims.py --check` on every committed table; tests/test_claims.py
runs it)."""

from __future__ import annotations

import json
from pathlib import Path

from orgnav_jax.tables import pages
from orgnav_jax.tables.claims import claims_table, not_converged_note
from orgnav_jax.tables.convergence_page import table_convergence
from orgnav_jax.tables.layout import existing_results, pretrain_dir, run_dir
from orgnav_jax.tables.provenance import PROVENANCE_FILE, provenance_table, read_provenance
from orgnav_jax.tables.rows import Row, lr_tag
from orgnav_jax.tables.runs import check_run_scenes, read_results, read_table_dir
from orgnav_jax.tables.table import table_text

# tables made before provenance.md existed do not have it: --check compares it where present
OPTIONAL_FILES = ("provenance.md",)


def expected_files(out: Path) -> dict[str, str]:
    """results.json, table.md, claims.md and provenance.md as the runs' files give them;
    with the spec's "converged": true also convergence.md, and claims.md names the rows
    that have not converged (claims.not_converged_note)."""
    spec, results, episodes = read_table_dir(out)
    lr = lr_tag(spec["rows"])
    files = {"results.json": json.dumps(results, indent=1),
             "table.md": table_text(results),
             "claims.md": claims_table(results, episodes, lr, spec),
             "provenance.md": provenance_table(out)}
    if spec.get("converged"):
        files["convergence.md"], not_converged = table_convergence(out, spec)
        files["claims.md"] += not_converged_note(lr, spec, not_converged)
    return files


def write_all(out: Path) -> dict[str, str]:
    """Write the generated files of `out` (expected_files) from its runs' files (all
    read and checked first: a bad file writes nothing) -> their texts."""
    files = expected_files(out)
    pages.write_pages({out / name: text for name, text in files.items()})
    return files


def check(out: Path) -> list[str]:
    """The files of `out` that differ from what its runs give (empty: all agree)."""
    return pages.differences({out / name: text for name, text in expected_files(out).items()},
                             optional=[out / name for name in OPTIONAL_FILES])


def check_or_write(out: Path, check_only: bool) -> int:
    """`claims.py [--check] TABLE`: write the table's files, or compare them (exit 1 on a
    difference)."""
    files = expected_files(out)
    return pages.regenerate({out / name: text for name, text in files.items()}, check_only,
                            optional=[out / name for name in OPTIONAL_FILES])


def write_table(out: Path, results: dict[str, dict[str, dict]]) -> str:
    """A table without a spec (rows given on the command line): OUT/table.md (table_text)
    and OUT/results.json (results[row][seed] = overall) -> table.md's text."""
    text = table_text(results)
    pages.write_pages({out / "table.md": text,
                       out / "results.json": json.dumps(results, indent=1)})
    return text


def check_run_files(out: Path, rows: list[str], seeds: list[int],
                    scenes: str | None = None) -> None:
    """Before any work: every run's results and provenance.json that exist can be read
    (a truncated provenance.json would otherwise stop the table after an evaluation
    wrote its results); with `scenes` (spec.table_scenes of the table's config), every
    run already in OUT/runs (of these rows or of earlier invocations) and every result
    is on those scenes (a table resumed across the default scene preset's change put
    runs of two presets into one row)."""
    if scenes is not None and (out / "runs").is_dir():
        for run in sorted((out / "runs").iterdir()):
            check_run_scenes(run, scenes)
    for name in rows:
        row = Row.of(name)
        for seed in seeds:
            results = existing_results(out, row, seed)
            if results is not None:
                read_results(results, "test", scenes)
            base_dir = run_dir(out, row, seed)
            read_provenance(base_dir / PROVENANCE_FILE)
            if row.pretrains:
                read_provenance(pretrain_dir(out, row.base, seed) / PROVENANCE_FILE)
            if row.is_tpn:
                read_provenance(base_dir / "tpn" / PROVENANCE_FILE)
