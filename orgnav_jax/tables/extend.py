"""A table extended to convergence (a spec with "extends": BASE; docs/results.md,
"Amendment: rows not converged at 22 M"): each row of BASE that has finished (every seed
tested) is judged by the convergence rule on its own val curves and

- carried over (its run directories copied into OUT with their test results) when the
  rule says it has converged, or cannot judge it (SAVN: one seed per program);
- extended when the rule says it has not converged: its run directories are copied into
  OUT without their test results and TPN, to train on (run_table.py) under the trainer's
  stop criterion (--until-converged), the spec's total_env_steps being the cap, from
  their checkpoint at BASE's last evaluation;
- left for a later run while BASE is still training it, or while a run to copy lacks
  that checkpoint (a checkout without BASE's checkpoints: restore them first).

(tables/spec.py checks the spec's fields against BASE's.)

    states = prepare(base, out, rows, seeds)   # {row: RowState}, runs copied into OUT
    state = row_state(base, "baseline", seeds, out)  # carry | extend | wait, and why
    copy_row(base, out, "baseline", seeds, carry=False)
    check_checkpoints(out, "baseline", seeds)  # before the copies train on

BASE's files are only read. A copy is made in a temporary directory beside its target and
renamed into place, so an interrupted copy leaves no half run; a run directory already in
OUT is never copied over.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from orgnav_jax.errors import UserError
from orgnav_jax.tables.convergence import check_runs
from orgnav_jax.tables.layout import existing_results, pretrain_dir, run_dir
from orgnav_jax.tables.provenance import record_provenance
from orgnav_jax.tables.rows import RANDOM, Row
from orgnav_jax.training.config import get_config
from orgnav_jax.training.run_dir import LOCK_FILE, saved_steps

CARRY, EXTEND, WAIT = "carry", "extend", "wait"
# what a run that trains on leaves behind: its test results (api.test_run writes the
# episodes beside them) and its TPN (trained again on the extended run)
TEST_OUTPUTS = ("test_results.json", "episodes-*-test-*.json", "tpn")


@dataclasses.dataclass(frozen=True)
class RowState:
    """What an extended table does with a base row: `action` (CARRY, EXTEND or WAIT) and
    `why` in a few words (run_table.py prints it)."""
    action: str
    why: str

    def describe(self, row: str, base: str | Path) -> str:
        """One line for run_table.py: what happens to `row` of table `base`, and why."""
        return f"{row}: " + {
            CARRY: f"carried over from {base}",
            EXTEND: f"trains on from {base}'s runs until the convergence rule holds",
            WAIT: "left for a later run"}[self.action] + f" ({self.why})"


def row_state(base: Path, row: str, seeds: list[int], out: Path) -> RowState:
    """What to do with navigation row `row` (a base row, or random) of table BASE; a row
    to extend waits while a run not yet copied into OUT lacks its checkpoint at BASE's
    last evaluation (training on from step 0 would silently be another experiment)."""
    missing = [s for s in seeds if existing_results(base, row, s) is None]
    if missing:
        return RowState(WAIT, f"seed {missing[0]} not tested in {base} yet")
    if row == RANDOM:
        return RowState(CARRY, "the random policy, nothing to train")
    if get_config(row).savn:
        return RowState(CARRY, "not judged: SAVN trains one seed per program, the rule "
                               "judges seeds trained together")
    try:           # ValueError: the rule cannot judge the runs (and says why)
        v = check_runs([run_dir(base, row, s) for s in seeds])
    except ValueError as err:
        return RowState(CARRY, f"not judged: {err}")
    if v.converged:
        return RowState(CARRY, f"converged at B' = {v.budget:,}")
    for seed in seeds:
        run = run_dir(base, row, seed)
        steps = saved_steps(run)
        if not run_dir(out, row, seed).exists() and v.env_steps not in steps:
            return RowState(WAIT, f"not converged at {v.env_steps:,} env steps, but "
                                  f"{run / 'checkpoints'} has no checkpoint of that step "
                                  f"to train on from (newest: "
                                  f"{f'{steps[-1]:,}' if steps else 'none'}); restore it")
    return RowState(EXTEND, f"not converged at {v.env_steps:,} env steps")


def copy_row(base: Path, out: Path, row: str, seeds: list[int], carry: bool) -> list[Path]:
    """Copy the runs of navigation row `row` (and a pre-trained row's pre-trainings) from
    table BASE into OUT: whole when `carry`, else without TEST_OUTPUTS. Runs already in
    OUT are left as they are. -> the run directories copied now."""
    ignore = shutil.ignore_patterns(LOCK_FILE, *(() if carry else TEST_OUTPUTS))
    copied = []
    for seed in seeds:
        pairs = [(run_dir(base, row, seed), run_dir(out, row, seed))]
        if Row.of(row).pretrains:
            pairs.append((pretrain_dir(base, row, seed), pretrain_dir(out, row, seed)))
        for src, dst in pairs:
            if dst.exists():
                continue
            tmp = dst.with_name(dst.name + ".copying")
            if tmp.exists():                 # an interrupted copy of this program's
                shutil.rmtree(tmp)
            shutil.copytree(src, tmp, ignore=ignore)
            tmp.rename(dst)
            record_provenance(dst, f"copied from {src}" + (
                " with its test results (carried over)" if carry else
                " without its test results and TPN, to train on under the convergence rule"))
            copied.append(dst)
    return copied


def check_checkpoints(out: Path, row: str, seeds: list[int]) -> None:
    """UserError when a run of `row` copied into OUT to train on has no checkpoint (lost
    with a new checkout): the resume would start it again from step 0."""
    for run in (run_dir(out, row, seed) for seed in seeds):
        if not saved_steps(run):
            raise UserError(f"{run}: no checkpoint to train on from (the extended table "
                            f"continues its runs); restore its checkpoints, or remove the "
                            f"run directory to copy it again from the base table")


def prepare(base: Path, out: Path, rows: list[str], seeds: list[int]) -> dict[str, RowState]:
    """Each navigation row of `rows` (a TPN row's base row, once; random) -> its RowState
    in table BASE, its runs copied into OUT (whole when carried over, without test
    results when extended; nothing for a row BASE has not finished)."""
    states = {}
    for base_row in dict.fromkeys(Row.of(name).base for name in rows):
        state = states[base_row] = row_state(base, base_row, seeds, out)
        if state.action != WAIT:
            copy_row(base, out, base_row, seeds, carry=state.action == CARRY)
    return states
