"""Compare the authors' optimal_action.json with our expert tables.

An authors' action a at state s for category c is consistent with our tables when it
starts SOME shortest path: Done where dist[s, c] == 0, otherwise
dist[next_state[s, a], c] == dist[s, c] - 1. Ties between equally short paths are
therefore never mismatches; `exact` counts where both picked the same action.
"""

from __future__ import annotations

import numpy as np

from orgnav_jax.constants import ACTIONS, CATEGORIES, DONE
from orgnav_jax.scenes.sceneset.fields import UNREACHABLE

EXAMPLES = 5


def compare_optimal(authors: np.ndarray, next_state: np.ndarray, dist: np.ndarray,
                    ours: np.ndarray, keys: list[str]) -> dict:
    """authors (S, C) int (-1 = no entry), next_state (S, A), dist (S, C), ours (S, C)
    of one scene (valid states only) -> counts and a few mismatch examples."""
    s, c = np.nonzero(authors >= 0)
    a = authors[s, c].astype(np.int64)
    d = dist[s, c].astype(np.int64)
    no_path = d >= UNREACHABLE
    done = a == DONE
    succ = dist[next_state[s, np.where(done, 0, a)], c].astype(np.int64)  # unused if Done
    fine = np.where(done, d == 0, (d > 0) & (succ == d - 1)) & ~no_path
    bad = np.flatnonzero(~fine & ~no_path)
    return {
        "compared": len(s),
        "exact": int((ours[s, c] == a).sum()),
        "on_shortest_path": int(fine.sum()),
        "mismatches": len(bad),
        "no_path_here": int(no_path.sum()),  # authors give an action, we see no path at all
        "examples": [
            {"state": keys[s[i]], "target": CATEGORIES[c[i]], "authors": ACTIONS[a[i]],
             "ours": ACTIONS[ours[s[i], c[i]]] if ours[s[i], c[i]] >= 0 else None,
             "dist": int(d[i])}
            for i in bad[:EXAMPLES]],
    }
