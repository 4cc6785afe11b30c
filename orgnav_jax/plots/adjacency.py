"""ORG's learned adjacency (or D-SP's prior graph) as a category heat map, and whether
it ranks the generator's co-occurrence pairs (scenes/synthetic/catalog.py ANCHORS) high
(the statistic, anchor_pair_report, is the tables library's: tables/adjacency.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES, CATEGORY_INDEX
from orgnav_jax.models.org import cooccurrence_adjacency
from orgnav_jax.plots.common import pyplot, save_png
# the statistic is the tables library's; plots re-exports it (plots/__init__.py)
from orgnav_jax.tables.adjacency import anchor_pair_report, anchor_pairs  # noqa: F401
from orgnav_jax.training.config import load_config


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
    plt = pyplot()
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
    # the trainer's modules (orbax, optax: seconds) on first use: `import orgnav_jax.plots`
    # (the curves, the tables' figures) does without them
    from orgnav_jax.training.runs import load_run_policy, scenes_for
    cfg = load_config(run_dir)
    if cfg.model in ("dsp", "dsp_replace"):
        present = np.asarray(scenes_for(cfg).split_view("train").present)
        return cooccurrence_adjacency(present), cfg.model
    if cfg.model != "org":
        raise ValueError(f"run {run_dir} trains model {cfg.model!r}, which has no adjacency "
                         "matrix (only 'org' learns one; 'dsp' uses a fixed prior)")
    _, params, cfg = load_run_policy(run_dir, best=best)
    return find_adjacency(params), cfg.model


# ---- learning curves -----------------------------------------------------------------
