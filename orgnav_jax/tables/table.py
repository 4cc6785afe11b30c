"""table.md: a table's rows as mean ± sample std over seeds (stats.mean_std), the TPN
rows' success gain over their base row paired by seed (mean ± sample std of the per-seed
differences), the failure analysis, and the pre-training budget of pre-trained rows."""

from __future__ import annotations

import numpy as np

from orgnav_jax.tables import stats
from orgnav_jax.tables.rows import Row

METRICS = ("success", "spl", "success_L5", "spl_L5")
# failure analysis columns: (result key, column label, scale); see docs/evaluation.md
FAILURE_METRICS = (("wrong_done", "wrong Done", 100), ("timeout", "timeout", 100),
                   ("revisits", "revisits/ep", 1), ("failed_moves", "failed moves/ep", 1))


def paired_gain(results: dict, row: str) -> str:
    """A TPN row's success minus its base row's, per seed: 'mean ± sample std' (percent
    points), or '' for rows without a base or without shared seeds."""
    r = Row.of(row)
    if not r.is_tpn:
        return ""
    d, seeds = stats.paired(results, row, r.base)
    return f"{d.mean():+.1f} ± {stats.sample_std(d):.1f}" if seeds else ""


def mean_std(by_seed: dict[str, dict], key: str, scale: float = 100.0) -> str:
    """'mean ± sample std' of one metric over seeds, or '-' where a seed's results lack
    it (results of runs made before the metric existed)."""
    if not by_seed or any(key not in r for r in by_seed.values()):
        return "-"
    return stats.mean_std(scale * np.array([r[key] for r in by_seed.values()], np.float64))


def table_text(results: dict[str, dict[str, dict]]) -> str:
    """results[row][seed] = metrics -> markdown table of mean ± sample std over seeds:
    METRICS in percent; TPN rows also show their success gain over their base row,
    paired by seed; then the failure analysis (FAILURE_METRICS: wrong Done and timeout
    in percent of episodes, revisits and failed moves per episode; '-' for older
    results). Rows whose seeds were pre-trained (runs.pretrain_budget) are marked † and
    their pre-training's budget is stated under the table (pretrain_notes)."""
    head = ["row", "seeds", "Success", "SPL", "Success (L>=5)", "SPL (L>=5)",
            "gain vs base"] + [label for _, label, _ in FAILURE_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row, by_seed in results.items():
        cells = [mean_std(by_seed, m) for m in METRICS] + [paired_gain(results, row)]
        cells += [mean_std(by_seed, k, scale) for k, _, scale in FAILURE_METRICS]
        mark = " †" if any("pretrain_samples" in r for r in by_seed.values()) else ""
        lines.append(f"| {row}{mark} | {len(by_seed)} | " + " | ".join(cells) + " |")
    notes = pretrain_notes(results)
    return "\n".join(lines) + "\n" + ("\n" + "\n".join(notes) + "\n" if notes else "")


def pretrain_notes(results: dict[str, dict[str, dict]]) -> list[str]:
    """One line per row marked † in table_text: its pre-training's budget per seed (the
    pretrain_budget fields of its results), extra supervision the other rows lack."""
    out = []
    for row, by_seed in results.items():
        got = {s: r for s, r in by_seed.items() if "pretrain_samples" in r}
        if not got:
            continue
        span = lambda key: "-".join(f"{v:,}" for v in sorted({r[key] for r in got.values()}))
        acc = {s: r for s, r in got.items() if "pretrain_val_accuracy" in r}
        out.append(f"† {row}: before the table's A2C budget, each seed's visual transformer "
                   f"was pre-trained with supervision of the expert's actions on "
                   f"{span('pretrain_samples')} (state, target) samples (batches of "
                   f"{span('pretrain_batch')}; best val accuracy "
                   f"{mean_std(acc, 'pretrain_val_accuracy')} %, {len(got)} seeds): "
                   "supervision the other rows do not get.")
    return out
