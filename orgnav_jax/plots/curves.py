"""Val learning curves of runs: rows of seeds, mean and band, from metrics.jsonl."""

from __future__ import annotations

import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from orgnav_jax.plots.common import pyplot, save_png
from orgnav_jax.training.run_dir import read_metrics


SEED_SUFFIX = re.compile(r"-s\d+$")
PERCENT = {"success", "spl", "success_L5", "spl_L5", "wrong_done", "timeout"}
BANDS = {"minmax": "min-max over seeds", "std": "mean ± std over seeds"}
LABELS = {"spl": "SPL", "success_L5": "success (L>=5)", "spl_L5": "SPL (L>=5)"}


class CurveError(ValueError):
    """Bad input for the curves: a one-line message that names the file."""


def row_of(run_dir: str | Path) -> str:
    """A run directory's row: its name without a -s<seed> suffix (baseline-s0 -> baseline)."""
    return SEED_SUFFIX.sub("", Path(run_dir).name) or Path(run_dir).name


def group_runs(specs: Iterable[str | Path]) -> dict[str, list[Path]]:
    """RUN_DIR or ROW=RUN_DIR entries -> {row: [run dirs]}, rows in order of appearance.
    A run given twice (the same directory, however spelled) is a CurveError: it would
    count as two seeds of its row."""
    rows: dict[str, list[Path]] = {}
    seen: dict[Path, str] = {}
    for spec in specs:
        text = str(spec)
        row, eq, path = text.partition("=")
        if not eq or not row or "/" in row:     # a plain path (which may contain '=')
            row, path = row_of(text), text
        key = Path(path).resolve()
        if key in seen:
            raise CurveError(f"{path}: given twice ({seen[key]} and {text}): each run is one "
                             "seed of its row")
        seen[key] = text
        rows.setdefault(row, []).append(Path(path))
    return rows


def read_val_curve(run_dir: str | Path, metrics: Sequence[str]) -> dict[str, np.ndarray]:
    """A run's val records in metrics.jsonl -> {"env_steps": (K,), metric: (K,)}, sorted by
    env steps; where a resumed run logged a step twice, the later record wins."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CurveError(f"{run_dir}: no such run directory")
    path = run_dir / "metrics.jsonl"
    if not path.is_file():
        raise CurveError(f"{path}: missing (not a training run directory?)")
    if not path.read_text().strip():
        raise CurveError(f"{path}: empty (the run has not logged anything yet)")
    try:
        records = read_metrics(run_dir)          # the typed reader of metrics.jsonl
    except ValueError as err:
        raise CurveError(str(err)) from None
    by_step: dict[int, dict] = {}
    for rec in records:
        if rec["kind"] == "val":
            by_step[rec["env_steps"]] = rec
    if not by_step:
        raise CurveError(f"{path}: no val records (kind 'val') yet")
    steps = sorted(by_step)
    out = {"env_steps": np.asarray(steps, np.int64)}
    for m in metrics:
        missing = [s for s in steps if not isinstance(by_step[s].get(m), (int, float))]
        if missing:
            raise CurveError(f"{path}: the val record at env step {missing[0]} has no "
                             f"numeric {m!r}")
        out[m] = np.asarray([by_step[s][m] for s in steps], np.float64)
    return out


def aggregate(curves: Sequence[tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """Seeds' (env_steps (K_i,), values (K_i,)) -> the curve over the env steps all seeds
    share: {"env_steps", "mean", "std", "min", "max": (K,), "seeds": n, "dropped": number
    of (seed, step) values outside the common steps}. Pure numpy; CurveError when the
    seeds share no step."""
    if not curves:
        raise CurveError("no runs to aggregate")
    common = np.asarray(sorted(set.intersection(*(set(np.asarray(s).tolist())
                                                  for s, _ in curves))), np.int64)
    if common.size == 0:
        raise CurveError("the seeds share no val env step")
    vals = np.stack([np.asarray(v, np.float64)[np.argsort(s)][
        np.searchsorted(np.sort(s), common)] for s, v in curves])            # (n, K)
    return {"env_steps": common, "mean": vals.mean(0), "std": vals.std(0),
            "min": vals.min(0), "max": vals.max(0), "seeds": len(curves),
            "dropped": int(sum(len(s) for s, _ in curves) - vals.size)}


def load_curves(rows: Mapping[str, Sequence[str | Path]], metrics: Sequence[str]) -> dict:
    """{row: [run dirs]} -> {row: {metric: aggregate(...), "best": mean over seeds of each
    seed's best value of metrics[0], "runs": [dirs]}}."""
    out = {}
    for row, dirs in rows.items():
        runs = [read_val_curve(d, metrics) for d in dirs]
        try:
            out[row] = {m: aggregate([(r["env_steps"], r[m]) for r in runs]) for m in metrics}
        except CurveError as err:
            raise CurveError(f"row {row!r} ({', '.join(map(str, dirs))}): {err}") from None
        out[row]["best"] = float(np.mean([r[metrics[0]].max() for r in runs]))
        out[row]["runs"] = [str(d) for d in dirs]
    return out


def curves_summary(data: dict, metric: str) -> str:
    """Per row: seeds, val steps used, last common env step, final and best `metric`
    (mean over seeds; best = each seed's best val value, averaged)."""
    scale, unit = (100.0, " %") if metric in PERCENT else (1.0, "")
    lines = [f"{'row':<24} {'seeds':>5} {'val steps':>9} {'last env step':>13} "
             f"{'final ' + metric + unit:>16} {'best ' + metric + unit:>16}"]
    for row, d in data.items():
        a = d[metric]
        lines.append(f"{row:<24} {a['seeds']:>5} {a['env_steps'].size:>9} "
                     f"{int(a['env_steps'][-1]):>13,} {scale * a['mean'][-1]:>16.1f} "
                     f"{scale * d['best']:>16.1f}")
    return "\n".join(lines)


def plot_curves(run_dirs: Iterable[str | Path] | Mapping[str, Sequence[str | Path]],
                out: str | Path, metrics: Sequence[str] = ("success", "spl"),
                band: str = "minmax", quiet: bool = False) -> dict:
    """Draw val `metrics` (one panel each) against env steps and write a PNG to `out`.

    run_dirs: run directories (grouped into rows by row_of; "ROW=DIR" names the row) or
    {row: [run dirs]}. One line per row: the mean over its seeds at their common env
    steps, with a band (BANDS). Unless quiet, prints the summary (curves_summary of
    metrics[0]) and a note for rows whose seeds' val steps differ (only the common steps
    are drawn). -> load_curves' data. CurveError for bad inputs (one line, names the file).
    """
    if band not in BANDS:
        raise CurveError(f"band must be one of {sorted(BANDS)}, got {band!r}")
    if not metrics:
        raise CurveError("no metrics to plot")
    rows = dict(run_dirs) if isinstance(run_dirs, Mapping) else group_runs(run_dirs)
    if not rows:
        raise CurveError("no run directories given")
    data = load_curves(rows, metrics)
    plt = pyplot()
    fig, axes = plt.subplots(1, len(metrics), figsize=(6 * len(metrics), 4.5), squeeze=False)
    for ax, m in zip(axes[0], metrics):
        scale = 100.0 if m in PERCENT else 1.0
        for i, (row, d) in enumerate(data.items()):
            a = d[m]
            lo, hi = ((a["min"], a["max"]) if band == "minmax"
                      else (a["mean"] - a["std"], a["mean"] + a["std"]))
            color = f"C{i % 10}"
            ax.plot(a["env_steps"], scale * a["mean"], color=color,
                    marker="o" if a["env_steps"].size == 1 else None, markersize=4,
                    label=f"{row} (n={a['seeds']})")
            ax.fill_between(a["env_steps"], scale * lo, scale * hi, color=color, alpha=0.2,
                            linewidth=0)
        ax.set_xlabel("env steps")
        if max(d[m]["env_steps"].max() for d in data.values()) >= 1e6:   # "5 M", not 1e7
            ax.xaxis.set_major_formatter(lambda x, _: f"{x / 1e6:g} M" if x else "0")
        name = LABELS.get(m, m)
        ax.set_ylabel(f"val {name}" + (" (%)" if m in PERCENT else ""))
        seeds = {d[m]["seeds"] for d in data.values()}
        ax.set_title(f"val {name}: one seed per row" if seeds == {1} else
                     f"val {name}: mean over seeds, band = {BANDS[band]}", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_png(fig, Path(out), dpi=110)
    if not quiet:
        for row, d in data.items():
            a = d[metrics[0]]
            if a["dropped"]:
                print(f"note: row {row!r}: its seeds' val steps differ; drawn at the "
                      f"{a['env_steps'].size} steps all share ({a['dropped']} values of "
                      "single seeds left out)", file=sys.stderr)
        print(curves_summary(data, metrics[0]))
    return data
