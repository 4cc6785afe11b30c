"""The learned adjacency's statistic: whether ORG's A ranks the generator's
co-occurrence pairs (scenes/synthetic/catalog.py ANCHORS) above the rest
(anchor_pair_report), and the adjacency.json a run keeps of it (its matrix and report,
so that a page recomputes the report without the checkpoint: read_adjacency)."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np

from orgnav_jax.constants import CATEGORIES, CATEGORY_INDEX, NUM_CATEGORIES, TARGETS
from orgnav_jax.errors import read_field, read_json, read_object
from orgnav_jax.scenes.synthetic.catalog import ANCHORS
from orgnav_jax.tables.layout import run_dir

ADJACENCY_FILE = "adjacency.json"


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


def adjacency_doc(A, graph: str) -> dict:
    """What RUN/adjacency.json holds: the matrix (rounded to 6 decimals) and its report."""
    doc = {"graph": graph, "A": np.asarray(A, np.float64).round(6).tolist()}
    doc["report"] = anchor_pair_report(np.asarray(doc["A"]))
    return doc


def read_adjacency(path: Path) -> dict:
    """An adjacency.json whose stored report must equal the one its matrix gives."""
    doc = read_object(read_json(path, "an adjacency JSON"), path)
    A = read_field(doc, "A", path)
    try:
        A = np.asarray(A, np.float64)
    except (TypeError, ValueError):
        A = None
    if A is None or A.shape != (NUM_CATEGORIES, NUM_CATEGORIES) or not np.isfinite(A).all():
        raise ValueError(f"{path}: field 'A': expected a {NUM_CATEGORIES} x {NUM_CATEGORIES} "
                         "matrix of finite numbers")
    again = anchor_pair_report(A)
    report = read_field(doc, "report", path)
    if json.dumps(again, sort_keys=True) != json.dumps(report, sort_keys=True):
        raise ValueError(f"{path}: the stored report differs from what its matrix gives")
    return report


def adjacency_reports(table_dir: Path, row: str, seeds) -> dict[str, dict]:
    """{seed: report} of the runs <row>-s<seed> of table_dir that carry adjacency.json."""
    paths = {s: run_dir(table_dir, row, s) / ADJACENCY_FILE for s in seeds}
    return {s: read_adjacency(p) for s, p in paths.items() if p.exists()}


def adjacency_lines(head: str, reports: dict[str, dict]) -> list[str]:
    """Table lines of one group of runs: a line per seed and the mean AUC."""
    if not reports:
        return [f"{head} - | not measured yet | | |"]
    lines = [f"{head} {s} | {rep['anchor_auc']:.2f} | {rep['anchor']['higher']} of "
             f"{rep['anchor']['n']} | {rep['anchor']['p_value']:.3f} |"
             for s, rep in reports.items()]
    if len(reports) > 1:
        aucs = [rep["anchor_auc"] for rep in reports.values()]
        significant = sum(rep["anchor"]["p_value"] < 0.05 for rep in reports.values())
        lines.append(f"{head} **mean** | **{np.mean(aucs):.2f}** | p < 0.05 in "
                     f"{significant} of {len(aucs)} | |")
    return lines
