"""The statistics of every table, claim, sweep and check (docs/results.md, "The tables
library": which interval each page shows).

- spread over seeds: mean ± sample std (ddof 1; 0 for one value): mean_std;
- a paired comparison (row against reference row, per seed, or per episode of one
  seeded episode set): the differences (paired, by_episode), their mean and a 95% t
  interval of the mean (ddof 1: t_interval), the one-sided paired t-test's p for the
  claimed sign (one_sided_p), and the three-level verdict over seeds: "holds in every
  seed", "holds on average (k of n seeds)", "does not hold" (verdict); statistics gives
  them all at once;
- a 95% percentile bootstrap interval of the mean paired difference that resamples seeds
  and, within each, episodes (bootstrap_interval; BOOTSTRAP resamples, fixed generator).
"""

from __future__ import annotations

import numpy as np
from scipy import stats as sp

LEVEL = 0.95          # every interval's level
BOOTSTRAP = 2000      # bootstrap resamples


def sample_std(v) -> float:
    """The sample standard deviation (ddof 1); 0 for a single value."""
    v = np.asarray(v, np.float64)
    return float(v.std(ddof=1)) if len(v) > 1 else 0.0


def mean_std(v, digits: int = 1) -> str:
    """'mean ± sample std' of values (the spread over seeds every table shows)."""
    v = np.asarray(v, np.float64)
    return f"{v.mean():.{digits}f} ± {sample_std(v):.{digits}f}"


def t_quantile(p: float, df: int) -> float:
    return float(sp.t.ppf(p, df))


def t_interval(d, level: float = LEVEL) -> tuple[float, float] | None:
    """The t interval of the mean of differences d (n,) at `level` (sample std, ddof 1);
    None for fewer than two values."""
    d = np.asarray(d, np.float64)
    n = len(d)
    if n < 2:
        return None
    mean = float(d.mean())
    half = t_quantile((1 + level) / 2, n - 1) * (d.std(ddof=1) / np.sqrt(n))
    return (mean - half, mean + half)


def one_sided_p(d, sign: int) -> float | None:
    """The one-sided paired t-test's p of differences d (n,) for H1: sign * mean > 0;
    None for fewer than two values (0 or 1 when they do not vary)."""
    d = np.asarray(d, np.float64)
    n = len(d)
    if n < 2:
        return None
    se = d.std(ddof=1) / np.sqrt(n)
    if se > 0:
        return float(sp.t.sf(sign * float(d.mean()) / se, n - 1))
    return 0.0 if sign * float(d.mean()) > 0 else 1.0


def verdict(d, sign: int) -> tuple[int, str]:
    """(seeds holding, the verdict): "holds in every seed", "holds on average (k of n
    seeds)" or "does not hold" for paired differences d (n,) per seed and the claimed
    sign."""
    d = np.asarray(d, np.float64)
    k, n = int((sign * d > 0).sum()), len(d)
    if k == n:
        return k, "holds in every seed"
    if sign * float(d.mean()) > 0:
        return k, f"holds on average ({k} of {n} seeds)"
    return k, "does not hold"


def paired(results: dict, row: str, ref: str, metric: str = "success"):
    """results[row][seed] = summary -> (differences row - ref in points (n,), seeds) over
    the seeds both rows have, in seed order."""
    seeds = sorted(set(results.get(row, {})) & set(results.get(ref, {})), key=int)
    d = np.array([100 * (results[row][s][metric] - results[ref][s][metric]) for s in seeds])
    return d, seeds


def by_episode(a, b) -> np.ndarray:
    """Per-episode outcomes a, b (E,) of the same seeded episodes -> a - b in points."""
    return 100 * (np.asarray(a, np.float64) - np.asarray(b, np.float64))


def statistics(d: np.ndarray, sign: int) -> dict:
    """Paired differences (n,) and the claimed sign -> {n, differences (rounded), mean,
    std (sample; None for one), interval (t_interval), p (one_sided_p), seeds_holding,
    verdict, excludes_0 (the interval lies on one side of 0)}."""
    n = len(d)
    mean = float(d.mean())
    out = {"n": n, "differences": [round(float(x), 2) for x in d], "mean": mean,
           "std": float(d.std(ddof=1)) if n > 1 else None, "interval": t_interval(d),
           "p": one_sided_p(d, sign)}
    out["seeds_holding"], out["verdict"] = verdict(d, sign)
    lo_hi = out["interval"]
    out["excludes_0"] = bool(lo_hi and (lo_hi[0] > 0 or lo_hi[1] < 0))
    return out


def bootstrap_interval(episodes: dict, row: str, ref: str, seeds: list[str], metric: str,
                       resamples: int = BOOTSTRAP, level: float = LEVEL):
    """The percentile interval (points) of the mean paired difference, resampling seeds
    and, within each drawn seed, episodes (episodes[row][seed][metric]: per-episode
    outcomes); None if a run lacks per-episode outcomes or the two rows' episode sets
    differ in size."""
    diffs = []
    for s in seeds:
        a, b = episodes.get(row, {}).get(s), episodes.get(ref, {}).get(s)
        if a is None or b is None or len(a[metric]) != len(b[metric]):
            return None
        diffs.append(by_episode(a[metric], b[metric]))
    d = np.stack(diffs)                                   # (n seeds, E episodes)
    n, e = d.shape
    rng = np.random.default_rng(0)
    means = np.empty(resamples)
    for i in range(resamples):
        pick = rng.integers(0, n, n)
        cols = rng.integers(0, e, (n, e))
        means[i] = d[pick[:, None], cols].mean()
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def interval_text(iv) -> str:
    """'[lo, hi]' with signs, one decimal; '-' for no interval."""
    return f"[{iv[0]:+.1f}, {iv[1]:+.1f}]" if iv else "-"
