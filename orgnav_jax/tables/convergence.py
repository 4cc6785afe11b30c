"""The convergence rule: when a row has stopped learning (docs/results.md, "When a row
has converged"; written before any table's run was judged by it).

    curve = seed_mean_curve([read_val_curve(d) for d in run_dirs])
    verdict = judge(curve)                        # the quarter test at the last evaluation
    verdict = converged(curve)                    # the rule there: held since B, confirmed
    first = converged_at(curve)                   # the first evaluation where the rule says so
    stop = stop_when_converged()                  # the trainer's stop criterion (--until-converged)

The rule. A row is at least MIN_SEEDS seeds of one config trained in one program,
evaluated on val every few chunks with at least MIN_VAL_EPISODES episodes an evaluation
(1,000: 250 per room type, as the test protocol; one evaluation's seed mean is then good
to about +-1 point). Its curve is the seed-mean val success (points) at each evaluation
step all its seeds share.

- The quarter test at an evaluation (judge): of the curve's n evaluations up to there
  (n >= MIN_EVALUATIONS = 40: 8 M env steps at the tables' evaluation every 204,800), the
  mean of the last quarter (the last n // 4) is within TOLERANCE points (1) of the mean
  of the quarter before it (the n // 4 before those).
- The row **has converged at budget B** (converged) when the quarter test holds at the
  evaluation at B and at every evaluation after it up to at least CONFIRM x B (1.25 B):
  the trainer stops there. (Version 1 of the rule, commit 73ec38d, took the first
  evaluation where the quarter test held: it stopped a budget candidate, the Baseline at
  16 envs, seeds 100-101, at 8.2 M env steps; trained on, at 10 M its last quarter stood
  3.5 points above the quarter before: a curve that steps up after a flat stretch can
  pass one quarter test.)
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

# metrics.jsonl's typed reader itself, not tables.runs.val_records: runs imports the
# evaluation (jax), and api imports this module (its stop criterion) while staying jax-free
from orgnav_jax.training.run_dir import read_metrics

TOLERANCE = 1.0            # points of val success between the last two quarters
MIN_SEEDS = 2
MIN_VAL_EPISODES = 1000    # per evaluation: 250 per room type
MIN_EVALUATIONS = 40       # each quarter at least 10 evaluations: with 2 seeds of 1,000
                           # episodes the two quarters' difference is then good to about
                           # +-0.5 points (one standard deviation), so noise alone rarely
                           # passes or fails the 1-point test
CONFIRM = 1.25             # the quarter test holds from B to at least this x B


@dataclasses.dataclass(frozen=True)
class ValCurve:
    """One run's val evaluations, in step order: steps (n,) env steps, success (n,) in
    [0, 1], episodes (n,) evaluated per evaluation; `where` names the run."""
    where: str
    steps: np.ndarray
    success: np.ndarray
    episodes: np.ndarray


@dataclasses.dataclass(frozen=True)
class SeedMeanCurve:
    """The row's curve: steps (n,) shared by every seed, success (n,) their mean in
    points, `seeds` the runs it averages, `episodes` the fewest of any evaluation."""
    steps: np.ndarray
    success: np.ndarray
    seeds: int
    episodes: int


@dataclasses.dataclass(frozen=True)
class Verdict:
    """The quarter test (judge) or the rule (converged) at one evaluation: whether it
    holds, the evaluations counted, the env steps of the last one, the two quarters'
    means and their change (points; None when the curve is too short), `budget` (the
    rule: B, the env steps since which the quarter test has held at every evaluation;
    None where it does not hold there), and `why` in one line."""
    converged: bool
    evaluations: int
    env_steps: int
    last_quarter: float | None
    quarter_before: float | None
    change: float | None
    why: str
    budget: int | None = None


def val_curve(records: Sequence[dict], where: str) -> ValCurve:
    """The val records of one run's metrics (training/run_dir.read_metrics) -> its
    ValCurve. ValueError naming `where` when a val record lacks success or episodes, when
    the steps do not increase, or when there is no val record."""
    val = [r for r in records if r["kind"] == "val"]
    if not val:
        raise ValueError(f"{where}: no val evaluation (expected 'val' records in "
                         "metrics.jsonl)")
    for r in val:
        for key in ("success", "episodes"):
            if key not in r:
                raise ValueError(f"{where}: a val record at env step {r['env_steps']:,} "
                                 f"lacks {key!r}")
    steps = np.array([r["env_steps"] for r in val], np.int64)
    if (np.diff(steps) <= 0).any():
        raise ValueError(f"{where}: val records not in increasing env steps")
    success = np.array([r["success"] for r in val], np.float64)
    if not (np.isfinite(success) & (success >= 0) & (success <= 1)).all():
        raise ValueError(f"{where}: a val success outside [0, 1]")
    return ValCurve(where, steps, success,
                    np.array([r["episodes"] for r in val], np.int64))


def read_val_curve(run_dir: str | Path) -> ValCurve:
    """metrics.jsonl of a run directory -> its ValCurve (a line cut by a kill skipped)."""
    path = Path(run_dir) / "metrics.jsonl"
    return val_curve(read_metrics(run_dir, skip_broken=True), str(path))


def seed_mean_curve(curves: Sequence[ValCurve]) -> SeedMeanCurve:
    """The seeds' curves -> their mean at the evaluation steps they all have (a seed
    killed after its last save may hold an evaluation the others lack). ValueError when
    they share no step."""
    if not curves:
        raise ValueError("no runs to judge")
    common = set(curves[0].steps.tolist())
    for c in curves[1:]:
        common &= set(c.steps.tolist())
    if not common:
        raise ValueError("the runs share no val evaluation step: "
                         + ", ".join(c.where for c in curves))
    steps = np.array(sorted(common), np.int64)
    picks = [np.searchsorted(c.steps, steps) for c in curves]
    success = 100 * np.mean([c.success[p] for c, p in zip(curves, picks)], axis=0)
    episodes = int(min(c.episodes[p].min() for c, p in zip(curves, picks)))
    return SeedMeanCurve(steps, success, len(curves), episodes)


def span_means(curve: SeedMeanCurve, edges: Sequence[int]) -> list[float | None]:
    """The curve's mean (points) over the evaluations in each span (edges[i], edges[i+1]]
    of env steps; None for a span without one."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (curve.steps > lo) & (curve.steps <= hi)
        out.append(float(curve.success[inside].mean()) if inside.any() else None)
    return out


def seed_span_means(curves: Sequence[ValCurve], parts: int) -> list[float | None]:
    """Each run's mean val success (points) over the evaluations in each of `parts`
    equal spans of its own run (to its last evaluation), averaged over the runs: for
    seeds whose evaluation steps differ (SAVN's count the steps episodes took). None for
    a span some run has no evaluation in."""
    per_run = []
    for c in curves:
        edges = [round(int(c.steps[-1]) * i / parts) for i in range(parts + 1)]
        one = SeedMeanCurve(c.steps, 100 * c.success, 1, int(c.episodes.min()))
        per_run.append(span_means(one, edges))
    return [None if any(r[i] is None for r in per_run)
            else float(np.mean([r[i] for r in per_run])) for i in range(parts)]


def applicable(curve: SeedMeanCurve) -> str | None:
    """Why the rule cannot judge this curve (one line), or None when it can."""
    if curve.seeds < MIN_SEEDS:
        return (f"{curve.seeds} seed: the rule judges the mean of at least {MIN_SEEDS} "
                "seeds trained in one program")
    if curve.episodes < MIN_VAL_EPISODES:
        return (f"val evaluations of {curve.episodes:,} episodes: the rule needs at least "
                f"{MIN_VAL_EPISODES:,} (--eval-episodes-per-room-type 250)")
    return None


def judge(curve: SeedMeanCurve, upto: int | None = None,
          tolerance: float = TOLERANCE) -> Verdict:
    """The rule on the curve's first `upto` evaluations (all by default) -> Verdict.
    ValueError when the rule does not apply to the curve (applicable)."""
    reason = applicable(curve)
    if reason:
        raise ValueError(reason)
    n = len(curve.steps) if upto is None else upto
    if not 1 <= n <= len(curve.steps):
        raise ValueError(f"upto {upto}: expected 1 to {len(curve.steps)} evaluations")
    step = int(curve.steps[n - 1])
    if n < MIN_EVALUATIONS:
        return Verdict(False, n, step, None, None, None,
                       f"{n} evaluations: the rule needs at least {MIN_EVALUATIONS}")
    q = n // 4
    last = float(curve.success[n - q:n].mean())
    before = float(curve.success[n - 2 * q:n - q].mean())
    change = last - before
    converged = abs(change) <= tolerance
    why = (f"seed-mean val success {last:.1f} over the last quarter ({q} evaluations to "
           f"{step:,} env steps) against {before:.1f} the quarter before: {change:+.1f} "
           f"points, {'within' if converged else 'beyond'} {tolerance:g}")
    return Verdict(converged, n, step, last, before, change, why)


def converged(curve: SeedMeanCurve, upto: int | None = None,
              tolerance: float = TOLERANCE) -> Verdict:
    """The rule at the curve's evaluation `upto` (the last by default): the quarter test
    there, with `budget` B the first evaluation of the unbroken run of evaluations up to
    there where the quarter test holds, and converged when that run reaches CONFIRM x B."""
    n = len(curve.steps) if upto is None else upto
    last = judge(curve, n, tolerance)
    if not last.converged:
        return last
    first = n
    while first > MIN_EVALUATIONS and judge(curve, first - 1, tolerance).converged:
        first -= 1
    budget = int(curve.steps[first - 1])
    done = last.env_steps >= CONFIRM * budget
    why = (f"{last.why}; the quarter test has held since {budget:,} env steps, "
           + ("converged at B = " + f"{budget:,}" if done else
              f"confirmed at {CONFIRM:g} x that: {CONFIRM * budget:,.0f}"))
    return dataclasses.replace(last, converged=done, why=why, budget=budget if done else None)


def converged_at(curve: SeedMeanCurve, tolerance: float = TOLERANCE) -> Verdict | None:
    """The rule at the first evaluation where it says converged (its `budget` is the
    row's B), or None when it says so nowhere on the curve."""
    for n in range(MIN_EVALUATIONS, len(curve.steps) + 1):
        v = converged(curve, n, tolerance)
        if v.converged:
            return v
    return None


def check_runs(run_dirs: Sequence[str | Path]) -> Verdict:
    """The rule on the runs of one row (their metrics.jsonl), at their last shared
    evaluation; ValueError (one line) where it cannot judge them (too few seeds or val
    episodes: `applicable`; no evaluation step in common; a malformed metrics.jsonl)."""
    return converged(seed_mean_curve([read_val_curve(d) for d in run_dirs]))


def check_stop_rule(seeds: Sequence[int], eval_episodes_per_room_type: int,
                    room_types: int = 4) -> None:
    """ValueError (one line) when training these seeds with val evaluations of this size
    cannot be judged by the rule: fewer than MIN_SEEDS seeds in one program, or fewer
    than MIN_VAL_EPISODES episodes an evaluation."""
    if len(seeds) < MIN_SEEDS:
        raise ValueError(f"--until-converged judges the mean of at least {MIN_SEEDS} seeds "
                         f"trained in one program: give --seeds S1 S2 ...")
    if eval_episodes_per_room_type * room_types < MIN_VAL_EPISODES:
        raise ValueError(f"--until-converged: --eval-episodes-per-room-type "
                         f"{eval_episodes_per_room_type} gives val evaluations of "
                         f"{eval_episodes_per_room_type * room_types} episodes; the rule "
                         f"needs at least {MIN_VAL_EPISODES:,} (250 per room type)")


def stop_when_converged(tolerance: float = TOLERANCE
                        ) -> Callable[[Sequence[Sequence[dict]]], str | None]:
    """The trainer's stop criterion (training/driver.py: run_population's `stop`): given
    each seed's val records so far, a one-line reason to stop when the rule holds, else
    None."""
    def stop(histories: Sequence[Sequence[dict]]) -> str | None:
        curves = [val_curve(h, f"seed {i}") for i, h in enumerate(histories)]
        verdict = converged(seed_mean_curve(curves), tolerance=tolerance)
        return f"converged: {verdict.why}" if verdict.converged else None
    return stop
