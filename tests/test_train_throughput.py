"""benchmarks/train_throughput.py's FLOP columns when XLA gives no count (seen on a GPU)."""
from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "train_throughput.py"


def load():
    spec = importlib.util.spec_from_file_location("train_throughput", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module                 # its dataclasses look it up
    spec.loader.exec_module(module)
    return module


def test_an_unknown_flop_count_is_shown_as_unknown_not_as_a_number():
    tt = load()
    assert math.isnan(tt._flops(None)) and tt._flops({"flops": 12.0}) == 12.0
    assert tt._flops([{"flops": 1.0}, {"flops": 2.0}]) == 3.0
    assert tt._per_step(float("nan"), 64) is None            # no 0, no crash in round()
    assert tt._per_step(float("inf"), 64) is None
    assert tt._per_step(6400.0, 64) == 100
    assert tt._col(None, 8).strip() == "-" and len(tt._col(None, 8)) == 8
    assert tt._col(5e6, 10, 1e6) == "      5.00"
    row = {"_run_s": 2.0, "_steps": 100, "flops_per_env_step": None,
           "_timed": lambda repeats: 1.0}
    tt.retime(row, 1)                                         # best of both runs kept
    assert row["env_steps_per_s"] == 100.0 and row["gflops_per_s"] is None
    row.update(flops_per_env_step=1e9, _timed=lambda repeats: 4.0)
    tt.retime(row, 1)
    assert row["_run_s"] == 1.0 and row["gflops_per_s"] == 100.0


def test_a_row_that_cannot_fit_is_skipped_with_its_estimate(tiny_scenes, monkeypatch):
    """A row whose preflight memory estimate exceeds the available memory is not
    compiled: one line with both figures, in the table and the JSON (the default run
    once died after 12 minutes in XLA's RESOURCE_EXHAUSTED on VTNet at paper widths)."""
    from orgnav_jax.training import memory
    tt = load()
    scenes = tiny_scenes.split_view("train")
    monkeypatch.setattr(memory, "available_memory", lambda: (10_000_000, "available"))
    row = tt.time_row("small", "baseline", 16, scenes, 1, None, 1)
    assert row["skipped"].startswith("skipped: the memory estimate")
    assert row["estimate_gb"] > row["available_gb"] == 0.0
    rows = [row, dict(row, model="org")]
    assert tt.add_baseline_ratios(rows) == []                 # skipped rows get no ratio
    monkeypatch.setattr(memory, "available_memory", lambda: (10 ** 12, "available"))
    cfg = tt.row_config("small", None, model="baseline", num_envs=16)
    assert tt.memory_skip(cfg, scenes) is None
