"""What a table reads from a run directory, each file through one checked reader:

- results JSONs (test_results.json, val_results.json, tpn/test_<variant>.json), as
  api.evaluate writes them: every stored summary recomputed from the per-episode outcomes
  kept beside it (read_results);
- the val records of metrics.jsonl (val_records, and the picks the pages make of them:
  val_at, best_val, last_val);
- a pre-trained row's extra budget (pretrain_budget);
- a whole table directory: its spec and every run's results (read_table_dir).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orgnav_jax.errors import is_number, read_field, read_json, read_object, shown
from orgnav_jax.evaluation import episodes_from_record, summarize
from orgnav_jax.tables.layout import existing_results, pretrain_dir, run_dir
from orgnav_jax.tables.rows import Row
from orgnav_jax.tables.spec import read_table_spec, table_scenes
from orgnav_jax.training.config import load_config, load_pretrain_config
from orgnav_jax.training.run_dir import CONFIG_FILE, METRICS_FILE, is_run_dir, read_metrics


def read_results_doc(path: Path, split: str | None = None, scenes: str | None = None) -> dict:
    """A results JSON as api.evaluate writes it, checked: an object with an `overall`
    object of numbers; when it keeps `per_episode` outcomes, the summary recomputed from
    them must equal the stored one (and the arrays are kept under `_per`); with `split`
    and `scenes`, the ones it records (results written before they were recorded have
    none) must be those. ValueError naming the file otherwise."""
    doc = read_object(read_json(path, "a results JSON"), path)
    for field, want, what in (("split", split, "the split the table reports"),
                              ("scenes", scenes, "the table's scenes: its spec's config, "
                                                 "or the default scene preset")):
        got = doc.get(field)
        if want is not None and got is not None and got != want:
            raise ValueError(f"{path}: field {field!r}: expected {want!r} ({what}), got "
                             f"{shown(got)}")
    stored = read_object(read_field(doc, "overall", path), f"{path}: field 'overall'")
    bad = [k for k, v in stored.items() if not is_number(v)]
    if bad:
        raise ValueError(f"{path}: field 'overall': expected numbers, got {bad[0]!r}: "
                         f"{stored[bad[0]]!r}")
    if "per_episode" not in doc:
        return doc
    try:
        per = episodes_from_record(read_object(doc["per_episode"],
                                               f"{path}: field 'per_episode'"))
        again = summarize(per)
    except (KeyError, TypeError, IndexError, ValueError) as err:
        raise ValueError(f"{path}: field 'per_episode' is malformed "
                         f"({type(err).__name__}: {err})") from None
    bad = [k for k in stored if k in again and
           not np.isclose(stored[k], again[k], rtol=0, atol=1e-12)]
    if bad or set(again) != set(stored):
        raise ValueError(f"{path}: the stored summary differs from its per-episode "
                         f"outcomes in {bad or 'its keys'}")
    doc["_per"] = per
    return doc


def read_results(path: Path, split: str | None = None,
                 scenes: str | None = None) -> tuple[dict, dict | None]:
    """A results JSON -> (its stored overall summary, its per-episode arrays: success,
    spl, ... (E,) each; None for results written before per-episode outcomes were kept).
    The summary is recomputed from the per-episode outcomes and must equal the stored one
    (read_results_doc: ValueError naming the file otherwise; split, scenes: what it must
    record)."""
    doc = read_results_doc(path, split, scenes)
    return doc["overall"], doc.get("_per")


def run_scenes(run: Path) -> str | None:
    """The scenes a training or pre-training run directory's config names (as
    spec.table_scenes names a table's), through the config's typed reader; None where
    `run` holds no such run (a TPN run's are its base's)."""
    if not is_run_dir(run):
        return None
    doc = read_json(Path(run) / CONFIG_FILE, "a run config")
    stage = doc.get("stage", "nav") if isinstance(doc, dict) else None
    if stage not in ("nav", "pretrain"):
        return None
    cfg = load_config(run) if stage == "nav" else load_pretrain_config(run)
    return Path(cfg.scenes_dir).name if cfg.scenes_dir else cfg.scene_preset


def check_run_scenes(run: Path, scenes: str) -> None:
    """ValueError naming the run's config when it was trained on other scenes than the
    table's `scenes` (a table resumed across the default's change, or a spec naming
    another preset than its runs'), before anything is judged or trained."""
    got = run_scenes(run)
    if got is not None and got != scenes:
        raise ValueError(f"{Path(run) / CONFIG_FILE}: the run was trained on {got!r}, but "
                         f"the table's scenes are {scenes!r} (its spec's config, or the "
                         "default scene preset where it names none): a table's runs are "
                         "on one set of scenes; name theirs in the spec's config, or use "
                         "another --out")


def val_records(run_dir: Path, step: str = "env_steps", skip_broken: bool = False,
                need: tuple[str, ...] = ()) -> list[dict]:
    """The val records of a run's metrics.jsonl (training/run_dir.read_metrics, its typed
    reader; `step`: env_steps, or episodes for a TPN run), in file order; ValueError
    naming the file and the step when a val record lacks a field of `need`."""
    val = [r for r in read_metrics(run_dir, step, skip_broken=skip_broken)
           if r["kind"] == "val"]
    for r in val:
        missing = [k for k in need if k not in r]
        if missing:
            unit = "env step" if step == "env_steps" else step.rstrip("s")
            raise ValueError(f"{Path(run_dir) / METRICS_FILE}: the val record at {unit} "
                             f"{r[step]:,} lacks field(s) {missing}")
    return val


def val_at(run_dir: Path, steps: int) -> dict:
    """The first val record at or after `steps` env steps (a run stops at the end of the
    chunk that crosses its budget, so its last record is there)."""
    vals = [r for r in val_records(run_dir, need=("success",)) if r["env_steps"] >= steps]
    if not vals:
        raise ValueError(f"{Path(run_dir) / METRICS_FILE}: no val record at or after "
                         f"{steps:,} env steps")
    return vals[0]


def best_val(run_dir: Path, up_to: int) -> dict:
    """The best val record of a run up to `up_to` env steps (by success then SPL, as the
    trainer picks its best checkpoint)."""
    val = [r for r in val_records(run_dir, need=("success", "spl"))
           if r["env_steps"] <= up_to]
    if not val:
        raise ValueError(f"{Path(run_dir) / METRICS_FILE}: no val record up to env step "
                         f"{up_to:,}")
    return max(val, key=lambda r: (r["success"], r["spl"]))


def last_val(run_dir: Path, step: str = "env_steps") -> dict:
    """The last val record of a run ({} when it has none)."""
    val = val_records(run_dir, step)
    return val[-1] if val else {}


def pretrain_budget(out: Path, row: str, seed: int | str) -> dict:
    """What a row's seed got on top of the table's budget: for a row of PRETRAIN_ROWS
    (or a TPN row on one) its pre-training's samples (whole batches), batch and best val
    accuracy (from the pre-training's config.json and metrics.jsonl); {} for other rows
    and where the pre-training is not there."""
    r = Row.of(row)
    pre = pretrain_dir(out, r.base, seed)
    if not r.pretrains or not is_run_dir(pre):
        return {}
    cfg = load_pretrain_config(pre)
    val = [v["accuracy"] for v in val_records(pre, "samples", skip_broken=True)
           if "accuracy" in v]
    return {"pretrain_samples": cfg.total_samples,
            "pretrain_batch": cfg.pretrain_batch,
            **({"pretrain_val_accuracy": max(val)} if val else {})}


def read_table_dir(out: Path) -> tuple[dict, dict, dict]:
    """A table directory's spec and, from its runs' files (read_results: every summary
    checked against its per-episode outcomes), results[row][seed] = overall summary (with
    a pre-trained row's pretrain_budget beside it) and episodes[row][seed] = per-episode
    arrays (success, spl); results written before per-episode outcomes were kept are
    taken as stored, without episodes. Every run and result must be on the spec's scenes
    (check_run_scenes; the results' recorded scenes) and every result of the test split."""
    spec = read_table_spec(out)
    scenes = table_scenes(spec["config"])
    results: dict = {}
    episodes: dict = {}
    for row in spec["rows"]:
        for seed in spec["seeds"]:
            path = existing_results(out, row, seed)
            if path is None:
                continue
            check_run_scenes(run_dir(out, row, seed), scenes)
            stored, per = read_results(path, "test", scenes)
            if per is not None:
                episodes.setdefault(row, {})[str(seed)] = {
                    "success": per["success"], "spl": per["spl"]}
            results.setdefault(row, {})[str(seed)] = dict(
                stored, **pretrain_budget(out, row, seed))
    return spec, results, episodes
