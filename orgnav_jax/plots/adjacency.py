"""ORG's learned adjacency (or D-SP's prior graph) as a category heat map, and whether
it ranks the generator's co-occurrence pairs (scenes/synthetic/catalog.py ANCHORS) high."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES, CATEGORY_INDEX, TARGETS
from orgnav_jax.plots.common import save_png
from orgnav_jax.scenes.synthetic.catalog import ANCHORS


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
    if cfg.model in ("dsp", "dsp_replace"):
        from orgnav_jax.models.org import cooccurrence_adjacency
        from orgnav_jax.training.runs import scenes_for
        present = np.asarray(scenes_for(cfg).split_view("train").present)
        return cooccurrence_adjacency(present), cfg.model
    if cfg.model != "org":
        raise ValueError(f"run {run_dir} trains model {cfg.model!r}, which has no adjacency "
                         "matrix (only 'org' learns one; 'dsp' uses a fixed prior)")
    from orgnav_jax.training.runs import load_run_policy
    _, params, cfg = load_run_policy(run_dir, best=best)
    return find_adjacency(params), cfg.model


# ---- learning curves -----------------------------------------------------------------
