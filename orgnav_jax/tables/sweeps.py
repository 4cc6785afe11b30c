"""The val sweeps' records (docs/results.md, "What val chose"), each form with its one
typed reader, and the summary page of a val sweep:

- a val sweep ({variant: {seed: {success, spl, env_steps, row, overrides}}}: written by
  experiments/val_sweep.py, and by savn_act_sweep.py with its acts as variants): read_sweep;
  OUT/<name>.md, best val success and SPL per variant as mean ± sample std over its
  seeds (stats.mean_std): summary_text, sweep_pages;
- a TPN learning-rate sweep ({tpn_dir, split, scope, results: {lr: overall}}: written by
  experiments/tpn_lr_sweep.py): read_tpn_sweep.
"""

from __future__ import annotations

import json
from pathlib import Path

from orgnav_jax.errors import read_json, read_number, read_object, read_str
from orgnav_jax.tables import stats

TPN_SWEEP_KEYS = ("tpn_dir", "split", "scope", "results")


def read_sweep(path: Path) -> dict[str, dict]:
    """The typed reader of a val_sweep.py-form JSON: {variant: {seed: {success, spl: numbers,
    row: a string, overrides: an object}}}; ValueError naming the file and field."""
    doc = read_object(read_json(path, "a val sweep JSON"), path,
                      "a JSON object {variant: {seed: record}}")
    for variant, by_seed in doc.items():
        read_object(by_seed, f"{path}: variant {variant!r}", "an object {seed: record}")
        if not by_seed:
            raise ValueError(f"{path}: variant {variant!r} holds no run")
        for seed, record in by_seed.items():
            where = f"{path}: {variant!r} seed {seed!r}"
            if not seed.lstrip("-").isdigit():
                raise ValueError(f"{where}: expected an integer seed")
            read_object(record, where)
            for metric in ("success", "spl"):
                read_number(record, metric, where)
            read_str(record, "row", where)
            read_object(record.get("overrides"), f"{where}: field 'overrides'")
    return doc


def read_tpn_sweep(path: Path) -> dict[str, dict]:
    """The typed reader of a tpn_lr_sweep.py record -> its results {lr: {success, spl}};
    ValueError naming the file and field."""
    doc = read_object(read_json(path, "a TPN lr sweep JSON"), path)
    results = read_object(doc.get("results"), f"{path}: field 'results'")
    for lr, overall in results.items():
        where = f"{path}: results[{lr!r}]"
        try:
            float(lr)
        except ValueError:
            raise ValueError(f"{where}: expected a learning rate as the key") from None
        read_object(overall, where)
        for metric in ("success", "spl"):
            read_number(overall, metric, where)
    read_str(doc, "split", path)
    return results


def summary_text(results: dict[str, dict[str, dict]]) -> str:
    """OUT/<name>.md of a val sweep's results (read_sweep's form): per variant its seeds,
    best val success and SPL (points) as mean ± sample std over the seeds, and the env
    steps of each seed's best val record."""
    lines = ["| variant | seeds | best val success (mean ± sample std) | best val SPL "
             "(mean ± sample std) | at env steps |", "|---|---|---|---|---|"]
    for variant, by_seed in results.items():
        s = [100 * r["success"] for r in by_seed.values()]
        p = [100 * r["spl"] for r in by_seed.values()]
        steps = ", ".join(f"{r['env_steps'] / 1e6:.2f} M" for r in by_seed.values())
        lines.append(f"| {variant} | {len(s)} | {stats.mean_std(s)} | {stats.mean_std(p)} | "
                     f"{steps} |")
    return "\n".join(lines) + "\n"


def sweep_pages(out: Path, name: str, results: dict[str, dict[str, dict]]) -> dict[Path, str]:
    """A val sweep's files: OUT/<name>.md (summary_text) and OUT/<name>.json (results)."""
    return {out / f"{name}.md": summary_text(results),
            out / f"{name}.json": json.dumps(results, indent=1)}
