"""The paper's claims, checked on a table's results: paired-by-seed differences.

    python experiments/claims.py experiments/results/table_5m/results.json --lr 1e-3

Reads run_table.py's results.json (results[row][seed] = test metrics) and prints, claim
by claim, the success difference (percentage points, test split) paired by seed: mean,
std over seeds and the seeds used, and whether the claim holds (the mean difference has
the claimed sign). A claim whose rows share no seed is reported as "not measured". Also
writes the markdown table next to the results (claims.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def claims(lr: str) -> list[tuple[str, str, str, int]]:
    """(claim, row, reference row, sign): the claim holds when sign * (row - ref) > 0."""
    tpn = lambda base, v="tpn": f"{base}+{v}@{lr}"
    return [
        ("IL > Baseline", "il", "baseline", 1),
        ("ORG > Baseline", "org", "baseline", 1),
        ("ORG + IL > ORG", "org_il", "org", 1),
        ("Baseline + TPN > Baseline", tpn("baseline"), "baseline", 1),
        ("ORG + IL + TPN > ORG + IL", tpn("org_il"), "org_il", 1),
        ("IL on every step < IL", "il_all", "il", -1),
        ("IL on failed moves < IL", "il_failed", "il", -1),
        ("TPN on every step < TPN (Baseline)", tpn("baseline", "tpn_all"), tpn("baseline"), -1),
        ("TPN on every step < TPN (ORG + IL)", tpn("org_il", "tpn_all"), tpn("org_il"), -1),
        ("TPN random target < TPN (Baseline)", tpn("baseline", "tpn_random"), tpn("baseline"),
         -1),
        ("TPN random target < TPN (ORG + IL)", tpn("org_il", "tpn_random"), tpn("org_il"), -1),
    ]


def paired(results: dict, row: str, ref: str, metric: str = "success"):
    """-> (differences in points (n,), seeds) over the seeds both rows have."""
    seeds = sorted(set(results.get(row, {})) & set(results.get(ref, {})), key=int)
    d = np.array([100 * (results[row][s][metric] - results[ref][s][metric]) for s in seeds])
    return d, seeds


def full_model_best(results: dict, lr: str) -> str:
    """Whether ORG + IL + TPN has the highest mean success of the rows on the same seeds."""
    full = f"org_il+tpn@{lr}"
    if full not in results:
        return "| full model (ORG + IL + TPN) best | not measured | | |"
    seeds = set(results[full])
    means = {row: np.mean([100 * r[s]["success"] for s in seeds]) for row, r in results.items()
             if seeds <= set(r)}
    best = max(means, key=means.get)
    gap = means[full] - max(v for k, v in means.items() if k != full)
    verdict = "holds" if best == full else f"does not hold (best: {best})"
    return (f"| full model (ORG + IL + TPN) best | {gap:+.1f} vs the next row | "
            f"{','.join(sorted(seeds, key=int))} | {verdict} |")


def table(results: dict, lr: str) -> str:
    lines = ["| claim | success difference (points), mean ± std | seeds | verdict |",
             "|---|---|---|---|"]
    for name, row, ref, sign in claims(lr):
        d, seeds = paired(results, row, ref)
        if not seeds:
            lines.append(f"| {name} | not measured | | |")
            continue
        holds = sign * d.mean() > 0
        std = f" ± {d.std():.1f}" if len(d) > 1 else " (one seed)"
        lines.append(f"| {name} | {d.mean():+.1f}{std} | {','.join(seeds)} | "
                     f"{'holds' if holds else 'does not hold'} |")
    lines.append(full_model_best(results, lr))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", help="run_table.py's results.json")
    ap.add_argument("--lr", default="1e-3", help="the TPN rows' test-time learning rate tag")
    args = ap.parse_args(argv)
    path = Path(args.results)
    text = table(json.loads(path.read_text()), args.lr)
    (path.parent / "claims.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
