"""The package's defaults are the values val chose (experiments/val_choices.py): the
record equals what the committed sweeps give, and the defaults equal the record."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def val_choices():
    spec = importlib.util.spec_from_file_location("val_choices",
                                                  ROOT / "experiments" / "val_choices.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_record_is_what_the_sweeps_give(val_choices):
    recorded = json.loads((val_choices.OUT / "choices.json").read_text())
    assert recorded == json.loads(json.dumps(val_choices.choices()))
    sweeps = val_choices.sweep_files()
    for sweep in sweeps:                                     # seeds no table uses
        seeds = {s for runs in json.loads(sweep.read_text()).values() for s in runs}
        assert seeds and all(int(s) >= 100 for s in seeds), (sweep.name, seeds)
    assert {"dropout.json", "il.json", "optim.json"} <= {p.name for p in sweeps}
    tpn = [json.loads(p.read_text()) for p in val_choices.OUT.glob("tpn_placement_*_tpn*.json")
           if not p.name.count(".lr")]
    assert all(d["split"] == "val" for d in tpn)


def test_defaults_are_the_choices(val_choices):
    from orgnav_jax import train as train_cli
    from orgnav_jax.tpn.config import TPN_LR, TestTime, TPNConfig
    from orgnav_jax.training.config import TABLE_DROPOUT, TrainConfig, get_config
    chosen = {k: v["value"] for k, v in val_choices.choices().items()}
    assert TABLE_DROPOUT == chosen["dropout"] == get_config("baseline").dropout
    spec = json.loads((ROOT / "experiments" / "tables" / "table_5m.json").read_text())
    assert spec["config"].get("dropout", TABLE_DROPOUT) == chosen["dropout"]
    for field in ("il_step", "il_norm", "il_weight"):
        assert getattr(TrainConfig(), field) == chosen[field], field
        assert getattr(get_config("org_il"), field) == chosen[field], field
    from orgnav_jax.training.config import TRAIN_PRESETS
    rows = [r for r in TRAIN_PRESETS if not get_config(r).savn]
    assert all(get_config(r).optim == chosen["optim"] for r in rows)
    for field, name in (("savn_inner_lr", "savn_inner_lr"), ("savn_steps", "savn_steps"),
                        ("savn_act", "savn_act"), ("optim", "savn_optim")):
        if name in chosen:       # the SAVN sweeps on the final SAVN code (issue 40)
            assert getattr(get_config("dsavn"), field) == getattr(get_config("savn"), field) \
                == chosen[name], field
    if "tpn_lr" in chosen:
        assert TPN_LR == TPNConfig().tpn_lr == TestTime().tpn_lr == chosen["tpn_lr"]
        assert all(float(row.partition("@")[2]) == chosen["tpn_lr"]
                   for row in spec["rows"] if "+" in row)
        assert TPNConfig().placement == TestTime().placement == chosen["tpn_placement"]
        assert TPNConfig().optim == chosen["tpn_stage2_optim"]
    if "pretrain_samples" in chosen:             # VTNet's sweep (issue 43)
        for field in ("pretrain_samples", "vtnet_mask", "pretrained_lr_scale"):
            assert getattr(get_config("vtnet"), field) == getattr(TrainConfig(), field) \
                == chosen[field], field
            assert field not in spec["config"], field
        assert get_config("vtnet_scratch").vtnet_mask == chosen["vtnet_mask"]
    args = train_cli.parser().parse_args(["--preset", "full"])
    assert train_cli.pipeline_tpn_fields(args) == {}        # the default: TPN_LR
