"""Pictures of trained runs: the ORG adjacency as a category heat map; learning curves;
one episode from above; the TPN memory's attention over an episode.

    python -m orgnav_jax.plots episode RUN_DIR [--episode K] [--split test] [--out PNG]

draws the room of episode K of the split's seeded episode set (or of --episodes FILE)
from above: every position, where the target is in view, the agent's path from start to
end (green star: success; red: wrong Done or timeout), its deadlock steps (x) and, for a
TPN run, the steps where the test-time update changed the policy (orange circles).

    python -m orgnav_jax.plots tpn-attention TPN_RUN_DIR [--episode K] [--step S] [--out PNG]

draws the paper's Fig. 3 (left) for episode K of a TPN run: the weights the TPN's read
put on each earlier step's memory slot, at every step (a heat map, darker = more weight,
with the deadlock and update steps marked), and at step S (default: the first update)
as bars labelled with the action taken there.

    python -m orgnav_jax.plots adjacency RUN_DIR [--out PNG] [--latest] [--json]

draws the learned adjacency A (C x C) of an `org` run (or the fixed prior graph of a `dsp`
run) with category names on both axes, marks the generator's co-occurrence pairs
(scenes/catalog.py ANCHORS) and prints whether A ranks them above the other pairs.

    python -m orgnav_jax.plots curves RUN_DIR... [--out PNG] [--metrics success spl]
                                      [--band minmax|std]

draws val success and SPL (one panel each) against env steps from each run's
metrics.jsonl: runs are grouped into rows by directory name without its -s<seed> suffix
(runs/baseline-s0, runs/baseline-s1 -> "baseline"; or name the row: ROW=DIR), one line
per row = the mean over its seeds at the env steps they share, with a band (min-max over
seeds, or mean +- std). Prints per row: seeds, final and best val success.
"""

from __future__ import annotations

import argparse
import itertools
import json
import re
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES, CATEGORY_INDEX, TARGETS
from orgnav_jax.errors import run_cli
from orgnav_jax.safe_write import check_output_file, is_own_png, write_png
from orgnav_jax.scenes.catalog import ANCHORS


def anchor_pairs() -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """The generator's co-occurrence rules as unordered category pairs:
    (object, anchor) pairs, e.g. RemoteControl-Television; and sibling pairs, objects
    that share an anchor, e.g. Toaster-CoffeeMachine (both placed near StoveBurner/Sink)."""
    direct = sorted({tuple(sorted((o, a))) for o, anchors in ANCHORS.items() for a in anchors})
    siblings = set()
    for o1, o2 in itertools.combinations(sorted(ANCHORS), 2):
        if set(ANCHORS[o1]) & set(ANCHORS[o2]):
            siblings.add(tuple(sorted((o1, o2))))
    return direct, sorted(siblings - set(direct))


def _same_room_pairs() -> set[tuple[str, str]]:
    """Unordered pairs of categories that are targets of a common room type."""
    return {tuple(sorted(p)) for cats in TARGETS.values()
            for p in itertools.combinations(cats, 2)}


def _subset_p_value(values: np.ndarray, upper: np.ndarray, draws: int = 10000) -> float:
    """One-sided p-value of mean(values) under the null that these pairs are a random
    subset of all pairs `upper` (seeded Monte Carlo)."""
    k = len(values)
    rng = np.random.default_rng(0)
    idx = np.argsort(rng.random((draws, len(upper))), axis=1)[:, :k]
    null = upper[idx].mean(1)
    return float((1 + np.sum(null >= values.mean() - 1e-12)) / (1 + draws))


def anchor_pair_report(A) -> dict:
    """Does A (C, C) rank the generator's co-occurrence pairs above the rest?

    A pair's value is the symmetric mean (A_ij + A_ji) / 2. For the anchor pairs and the
    sibling pairs (anchor_pairs): how many lie above the mean off-diagonal entry, their
    mean, and the p-value of that mean against random sets of as many pairs. The mean over
    the other same-room-type pairs (constants.TARGETS) separates "anchored objects are
    related" from "objects of one room type are".
    anchor_auc: the probability that an anchor pair's value exceeds that of another
    same-room-type pair (ties count half; 0.5 = chance, 1 = every anchor pair above).
    -> {"offdiag_mean", "offdiag_std", "same_room_mean", "pairs": [{"pair", "kind",
    "value", "percentile", "higher"}], "anchor": {"n", "higher", "mean", "p_value"},
    "sibling": {...}, "anchor_auc", "reflects": anchor p_value < 0.05}."""
    A = np.asarray(A, np.float64)
    C = len(CATEGORIES)
    if A.shape != (C, C):
        raise ValueError(f"adjacency must be ({C}, {C}), got {A.shape}")
    S = 0.5 * (A + A.T)
    upper = S[np.triu_indices(C, 1)]
    off_mean, off_std = float(upper.mean()), float(upper.std())
    direct, siblings = anchor_pairs()
    room = sorted(_same_room_pairs() - set(direct) - set(siblings))
    room_vals = np.array([S[CATEGORY_INDEX[a], CATEGORY_INDEX[b]] for a, b in room])
    room_mean = float(room_vals.mean())
    pairs, groups = [], {}
    for kind, group in (("anchor", direct), ("sibling", siblings)):
        vals = np.array([S[CATEGORY_INDEX[a], CATEGORY_INDEX[b]] for a, b in group])
        for (a, b), v in zip(group, vals):
            pairs.append({"pair": f"{a}-{b}", "kind": kind, "value": float(v),
                          "percentile": float((upper < v).mean()), "higher": bool(v > off_mean)})
        groups[kind] = {"n": len(vals), "higher": int((vals > off_mean).sum()),
                        "mean": float(vals.mean()), "p_value": _subset_p_value(vals, upper)}
    anchor_vals = np.array([S[CATEGORY_INDEX[a], CATEGORY_INDEX[b]] for a, b in direct])
    diff = anchor_vals[:, None] - room_vals[None, :]
    auc = float((diff > 0).mean() + 0.5 * (diff == 0).mean())
    return {"offdiag_mean": off_mean, "offdiag_std": off_std, "same_room_mean": room_mean,
            "pairs": pairs, **groups, "anchor_auc": auc,
            "reflects": bool(groups["anchor"]["p_value"] < 0.05)}


def format_report(rep: dict) -> str:
    """A short human-readable summary of anchor_pair_report."""
    lines = [(f"mean off-diagonal entry {rep['offdiag_mean']:+.4f} "
              f"(std {rep['offdiag_std']:.4f}); "
              f"mean over other same-room pairs {rep['same_room_mean']:+.4f}")]
    for kind in ("anchor", "sibling"):
        g = rep[kind]
        lines.append(f"{kind} pairs: {g['higher']}/{g['n']} above the off-diagonal mean, "
                     f"mean {g['mean']:+.4f} (p = {g['p_value']:.2g} against random pairs)")
    lines.append(f"AUC of anchor pairs against other same-room-type pairs: "
                 f"{rep['anchor_auc']:.2f} (0.5 = chance)")
    for p in rep["pairs"]:
        where = "above" if p["higher"] else "below"
        lines.append(f"  {p['kind']:7s} {p['pair']:28s} {p['value']:+.4f}  "
                     f"percentile {100 * p['percentile']:5.1f}%  {where}")
    lines.append("A reflects the anchor rules (anchor pairs significantly above random pairs, "
                 "p < 0.05)" if rep["reflects"] else
                 "A does not reflect the anchor rules (anchor pairs not significantly above "
                 "random pairs)")
    return "\n".join(lines)


def save_png(fig, out: Path, dpi: int = 120) -> Path:
    """Write a figure (safe_write.write_png: atomic, marked as ours, never over a file we
    did not write) and close it -> out."""
    import matplotlib.pyplot as plt
    try:
        return write_png(fig, out, dpi)
    finally:
        plt.close(fig)


def default_out(run_dir: str | Path, name: str, out: str | Path | None) -> Path:
    """The one rule of the picture commands: --out, else RUN_DIR/NAME (the first run's
    directory for curves), checked before any work (write_png's rules)."""
    if out is not None and not str(out).strip():
        raise ValueError("--out is empty: expected a .png path")
    path = Path(out) if out is not None else Path(run_dir) / name
    if path.suffix.lower() != ".png":
        raise ValueError(f"--out {path}: expected a .png path (pictures are PNG files)")
    check_output_file(path, is_own_png, "a PNG written by orgnav_jax")
    return path


def plot_adjacency(A, path, title: str = "ORG adjacency A", mark_pairs: bool = True) -> Path:
    """Draw A (C, C) as a heat map with category names (rows: attending category i,
    columns: attended category j) and write a PNG to `path`. The colour scale is symmetric
    around 0 and set by the off-diagonal entries (the diagonal may saturate); anchor pairs
    are marked with dots."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    A = np.asarray(A, np.float64)
    C = len(CATEGORIES)
    if A.shape != (C, C):
        raise ValueError(f"adjacency must be ({C}, {C}), got {A.shape}")
    off = A[~np.eye(C, dtype=bool)]
    vmax = float(np.abs(off).max()) or 1.0
    fig, ax = plt.subplots(figsize=(9, 8))
    im = ax.imshow(A, cmap="RdBu_r", vmin=-vmax, vmax=vmax)
    ax.set_xticks(range(C), CATEGORIES, rotation=90, fontsize=8)
    ax.set_yticks(range(C), CATEGORIES, fontsize=8)
    ax.set_xlabel("attended category j")
    ax.set_ylabel("category i")
    if mark_pairs:
        for a, b in anchor_pairs()[0]:
            i, j = CATEGORY_INDEX[a], CATEGORY_INDEX[b]
            ax.plot([j, i], [i, j], "k.", markersize=4)
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04,
                 label="A_ij (scale from off-diagonal entries)")
    ax.set_title(title)
    fig.tight_layout()
    return save_png(fig, Path(path))


def find_adjacency(variables) -> np.ndarray:
    """The learned (C, C) `adjacency` parameter in a model's variables
    ({"params": {"encoder": {"adjacency": ...}, ...}}); a clear error if there is none."""
    found = []

    def walk(tree, prefix):
        if hasattr(tree, "items"):
            for k, v in tree.items():
                walk(v, prefix + (str(k),))
        elif prefix and prefix[-1] == "adjacency":
            found.append((prefix, np.asarray(tree)))

    walk(variables, ())
    if len(found) != 1:
        raise ValueError(f"expected one 'adjacency' parameter, found "
                         f"{['/'.join(p) for p, _ in found] or 'none'}: only the 'org' "
                         "model learns an adjacency")
    return found[0][1]


def run_adjacency(run_dir: str | Path, best: bool = True) -> tuple[np.ndarray, str]:
    """-> (A, model name) of a run: the learned A of 'org', the prior graph of 'dsp'."""
    from orgnav_jax.training.config import load_config
    cfg = load_config(run_dir)
    if cfg.model == "dsp":
        from orgnav_jax.models.org import cooccurrence_adjacency
        from orgnav_jax.training.runs import scenes_for
        present = np.asarray(scenes_for(cfg).split_view("train").present)
        return cooccurrence_adjacency(present), "dsp"
    if cfg.model != "org":
        raise ValueError(f"run {run_dir} trains model {cfg.model!r}, which has no adjacency "
                         "matrix (only 'org' learns one; 'dsp' uses a fixed prior)")
    from orgnav_jax.training.runs import load_run_policy
    _, params, cfg = load_run_policy(run_dir, best=best)
    return find_adjacency(params), cfg.model


# ---- learning curves -----------------------------------------------------------------

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
    """RUN_DIR or ROW=RUN_DIR entries -> {row: [run dirs]}, rows in order of appearance."""
    rows: dict[str, list[Path]] = {}
    for spec in specs:
        text = str(spec)
        row, eq, path = text.partition("=")
        if not eq or not row or "/" in row:     # a plain path (which may contain '=')
            row, path = row_of(text), text
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
    from orgnav_jax.training.run_dir import read_metrics
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

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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


def trace_run_episode(run_dir: str | Path, episode: int = 0, split: str = "test",
                      episodes_file: str | None = None, episode_seed: int = 0,
                      per_room_type: int | None = None, test_time: dict | None = None) -> dict:
    """One episode of a run's policy (a training run, or a TPN run with its test-time
    updates; `test_time` overrides their fields, as evaluate's --when, --target, ...),
    step by step -> {"trace": evaluation.trace_episodes of it, "scenes": the split's
    SceneSet, "episode": the one-episode EpisodeSet, "name": the policy, "outcome": one of
    evaluation.OUTCOMES, "steps": the T steps the episode took, (T,) arrays of the trace
    (state, action, deadlock, ...; a TPN run adds "updated", the steps the test-time
    update took, and "tpn_attention" (T, T))}.
    The episode is number `episode` of the split's seeded set (as evaluate samples it),
    or of `episodes_file`."""
    from orgnav_jax import api, env, evaluation
    from orgnav_jax.constants import EPISODES_PER_ROOM_TYPE
    from orgnav_jax.episodes import load_episodes, sample_episodes
    from orgnav_jax.scenes.cache import device_split
    loaded = api.load_run(run_dir, **(test_time or {}))
    scenes = device_split(loaded.scene_preset, loaded.scene_seed, loaded.scenes_dir, split)
    episodes = (load_episodes(episodes_file, scenes) if episodes_file else
                sample_episodes(scenes, per_room_type or EPISODES_PER_ROOM_TYPE,
                                seed=episode_seed, split=split))
    if not 0 <= episode < len(episodes):
        raise ValueError(f"--episode {episode}: the {split} set has episodes 0..."
                         f"{len(episodes) - 1}")
    one = episodes.subset(np.array([episode]))
    trace = evaluation.trace_episodes(loaded.policy, loaded.params, scenes, one,
                                      env.EnvParams.evaluation())
    T = int(trace["running"][0].sum())          # running: True on the steps taken
    steps = {k: v[0][:T] for k, v in trace.items() if v.ndim >= 2}
    if "tpn_updates" in steps:
        steps["updated"] = np.diff(steps["tpn_updates"], prepend=0) > 0
    if "tpn_attention" in steps:
        steps["tpn_attention"] = steps["tpn_attention"][:, :T]
    return {"trace": trace, "scenes": scenes, "episode": one, "name": loaded.policy.name,
            "outcome": next(k for k in evaluation.OUTCOMES if trace[k][0]), "steps": steps}


def plot_episode(run_dir: str | Path, episode: int = 0, split: str = "test",
                 out: str | Path | None = None, **kw) -> Path:
    """Top view of one episode of a run (trace_run_episode): the room's positions, where
    the target is in view, the agent's path from start to end, its deadlock steps and the
    steps where TPN updated the policy -> the PNG path (default RUN_DIR/episode-K.png)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    got = trace_run_episode(run_dir, episode, split, **kw)
    steps, scenes, one, outcome = got["steps"], got["scenes"], got["episode"], got["outcome"]
    n, target = int(one.scene[0]), int(one.target[0])
    rows = scenes.state_slice(n)
    pose = np.asarray(scenes.pose)
    room_xz = pose[rows, :2]
    seen = np.asarray(scenes.visible)[rows, target]
    path = pose[steps["state"], :2]
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.scatter(*np.unique(room_xz, axis=0).T, s=6, c="0.85", label="positions")
    ax.scatter(*np.unique(room_xz[seen], axis=0).T, s=14, c="tab:green",
               label=f"{CATEGORIES[target]} in view")
    ax.plot(*path.T, "-", c="tab:blue", lw=1.5, alpha=0.8, label="path")
    ax.scatter(*path[0], marker="s", s=70, c="tab:blue", label="start", zorder=3)
    ax.scatter(*path[-1], marker="*", s=160, zorder=3,
               c="tab:green" if outcome == "success" else "tab:red", label=f"end: {outcome}")
    if steps["deadlock"].any():
        ax.scatter(*path[steps["deadlock"]].T, marker="x", s=50, c="tab:red",
                   label="deadlock step")
    if "updated" in steps and steps["updated"].any():
        ax.scatter(*path[steps["updated"]].T, s=90, facecolors="none",
                   edgecolors="tab:orange", lw=1.5, label="TPN update")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(f"{got['name']}: {scenes.scene_names[n]}, target {CATEGORIES[target]}, "
                 f"{len(path)} steps", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    return save_png(fig, Path(out) if out else Path(run_dir) / f"episode-{episode}.png")


def tpn_attention(run_dir: str | Path, episode: int = 0, split: str = "test", **kw) -> dict:
    """Where the TPN's memory read looked during one episode of a TPN run ->
    {"attention": (T, T) weights, row t = step t, column i = the memory slot of step i
    (its key r_i, its value r_{i+1} and p_i; only i < t can be read, k of them weigh),
    "updated": (T,) bool, the steps the test-time update took; "deadlock", "action"
    (T,); "name", "scene", "target", "outcome"}, T = the steps the episode took."""
    from orgnav_jax.errors import UserError
    got = trace_run_episode(run_dir, episode, split, **kw)
    steps = got["steps"]
    if "tpn_attention" not in steps:
        raise UserError(f"{run_dir}: a training run; TPN attention exists only for a TPN "
                        "(stage 2) run (train --stage tpn)")
    return {"attention": steps["tpn_attention"], "updated": steps["updated"],
            "deadlock": steps["deadlock"], "action": steps["action"], "name": got["name"],
            "scene": got["scenes"].scene_names[int(got["episode"].scene[0])],
            "target": CATEGORIES[int(got["episode"].target[0])], "outcome": got["outcome"]}


def plot_tpn_attention(run_dir: str | Path, episode: int = 0, split: str = "test",
                       out: str | Path | None = None, step: int | None = None,
                       **kw) -> tuple[Path, dict]:
    """The paper's Fig. 3 (left) for one episode of a TPN run (tpn_attention): left, the
    read's weights, step t (rows) over earlier steps i (columns), darker = more weight,
    with the update and deadlock steps marked; right, the weights at one step (`step`,
    default the first update, else the last step) over the earlier steps, labelled with
    the action taken there -> (the PNG path, default RUN_DIR/tpn-attention-K.png, and
    the tpn_attention dict)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from orgnav_jax.constants import ACTIONS
    att = tpn_attention(run_dir, episode, split, **kw)
    A, updated, T = att["attention"], att["updated"], len(att["updated"])
    if step is None:
        step = int(np.argmax(updated)) if updated.any() else T - 1
    if not 0 <= step < T:
        raise ValueError(f"--step {step}: the episode took steps 0...{T - 1}")
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained",
                                      gridspec_kw={"width_ratios": [1, 1.3]})
    im = left.imshow(A, cmap="Greys", vmin=0, vmax=max(float(A.max()), 1e-6),
                     origin="upper", interpolation="nearest")
    fig.colorbar(im, ax=left, fraction=0.046, label="attention weight p")
    for t in np.flatnonzero(att["deadlock"]):
        left.scatter(-1.2, t, marker="x", c="tab:red", s=25, clip_on=False)
    for t in np.flatnonzero(updated):
        left.scatter(-2.4, t, marker="o", facecolors="none", edgecolors="tab:orange",
                     s=30, clip_on=False)
    left.axhline(step, c="tab:blue", lw=0.8, alpha=0.6)
    left.set_xlim(-3, T - 0.5)
    left.set_xlabel("earlier step i (memory slot)")
    left.set_ylabel("step t   (x: deadlock, o: TPN update)")
    left.set_title(f"{att['name']}: {att['scene']}, target {att['target']}, "
                   f"{T} steps, {att['outcome']}", fontsize=9)
    past = np.arange(step)
    colours = ["tab:orange" if u else "tab:gray" for u in updated[:step]]
    right.bar(past, A[step, :step], color=colours)
    right.set_xticks(past)
    right.set_xticklabels([f"{i}:{ACTIONS[a]}" for i, a in zip(past, att["action"][:step])],
                          rotation=90, fontsize=6)
    right.set_ylabel("attention weight p")
    right.set_title(f"step {step}" + (" (TPN update)" if updated[step] else "") + (
        f": weights on steps 0...{step - 1}, action taken there (orange: updates)"
        if step else ": the first step, nothing to read yet"), fontsize=9)
    out = save_png(fig, Path(out) if out else Path(run_dir) / f"tpn-attention-{episode}.png")
    return out, dict(att, step=step)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m orgnav_jax.plots", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("adjacency", help="heat map of a run's ORG adjacency")
    p.add_argument("run_dir")
    p.add_argument("--out", default=None, help="PNG path (default RUN_DIR/adjacency.png)")
    p.add_argument("--latest", action="store_true",
                   help="use the latest checkpoint instead of the best-on-val one")
    p.add_argument("--json", action="store_true",
                   help="print the report as one JSON object (anchor p-value, anchor_auc, "
                        "pairs) on stdout; the 'wrote' line goes to stderr")
    e = sub.add_parser("episode", help="top view of one episode of a run (path, target, "
                                       "deadlock steps, TPN updates)")
    e.add_argument("run_dir", help="a training run or a TPN (stage 2) run directory")
    t = sub.add_parser("tpn-attention", help="the TPN memory's attention over an episode's "
                                             "earlier steps (the paper's Fig. 3, left)")
    t.add_argument("run_dir", help="a TPN (stage 2) run directory")
    t.add_argument("--step", type=int, default=None, help="the step whose weights the right "
                   "panel shows (default: the first TPN update, else the last step)")
    from orgnav_jax.tpn.config import TEST_TIME_FIELDS, add_tpn_arguments
    for sp, png in ((e, "episode-K.png"), (t, "tpn-attention-K.png")):
        sp.add_argument("--episode", type=int, default=0, help="index in the episode set")
        sp.add_argument("--split", choices=("val", "test"), default="test")
        sp.add_argument("--episodes", default=None, help="an episode file (default: the "
                        "seeded set evaluate samples)")
        sp.add_argument("--out", default=None, help=f"PNG path (default RUN_DIR/{png})")
        add_tpn_arguments(sp, TEST_TIME_FIELDS)   # a TPN run's test-time settings
    c = sub.add_parser("curves", help="val learning curves of runs, mean and band over seeds")
    c.add_argument("runs", nargs="+", metavar="RUN_DIR",
                   help="training run directories (or ROW=RUN_DIR); NAME-s<seed> -> row NAME")
    c.add_argument("--out", default=None,
                   help="PNG path (default: FIRST_RUN_DIR/curves.png)")
    c.add_argument("--metrics", nargs="+", default=["success", "spl"],
                   help="val record fields, one panel each (default: success spl)")
    c.add_argument("--band", choices=sorted(BANDS), default="minmax",
                   help="shaded band: min-max over seeds (default) or mean +- std")
    args = ap.parse_args(argv)
    if args.cmd in ("episode", "tpn-attention"):
        from orgnav_jax.tpn.config import tpn_overrides_from_args
        kw = dict(episodes_file=args.episodes, test_time=tpn_overrides_from_args(args))
    if args.cmd == "episode":
        out = default_out(args.run_dir, f"episode-{args.episode}.png", args.out)
        out = plot_episode(args.run_dir, args.episode, args.split, out, **kw)
        print(f"wrote {out}")
        return 0
    if args.cmd == "tpn-attention":
        out = default_out(args.run_dir, f"tpn-attention-{args.episode}.png", args.out)
        out, att = plot_tpn_attention(args.run_dir, args.episode, args.split, out,
                                      args.step, **kw)
        w = att["attention"][att["step"]]
        top = [f"{i} ({w[i]:.2f})" for i in np.argsort(-w)[:3] if w[i] > 0]
        print(f"wrote {out}\n{int(att['updated'].sum())} TPN updates in "
              f"{len(att['updated'])} steps; step {att['step']} reads most from steps "
              + (", ".join(top) or "none (no earlier step)"))
        return 0
    if args.cmd == "curves":
        rows = group_runs(args.runs)
        out = default_out(next(iter(rows.values()))[0], "curves.png", args.out)
        try:
            plot_curves(rows, out, args.metrics, args.band)
        except CurveError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
        print(f"wrote {out}")
        return 0
    out = default_out(args.run_dir, "adjacency.png", args.out)
    try:
        A, name = run_adjacency(args.run_dir, best=not args.latest)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    title = f"{'learned ORG adjacency' if name == 'org' else 'D-SP prior graph'}: {args.run_dir}"
    plot_adjacency(A, out, title)
    report = anchor_pair_report(A)
    if args.json:
        print(f"wrote {out}", file=sys.stderr)
        print(json.dumps(dict(report, run_dir=str(args.run_dir), graph=name)))
    else:
        print(f"wrote {out}")
        print(format_report(report))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
