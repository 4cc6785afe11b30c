"""The package's defaults are the values val chose (orgnav_jax/tables/choices.py, run by
experiments/val_choices.py): the record equals what the committed sweeps give, and the
defaults equal the record."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import EXPERIMENTS, experiment_script

from orgnav_jax.tables import choices
from orgnav_jax.tables.rows import Row

ROOT = Path(__file__).resolve().parents[1]
OUT = EXPERIMENTS / "results" / "val_choices"


@pytest.fixture(scope="module")
def val_choices():
    """experiments/val_choices.py, the command line."""
    return experiment_script("val_choices")


def test_the_record_is_what_the_sweeps_give(val_choices):
    recorded = json.loads((OUT / "choices.json").read_text())
    assert recorded == json.loads(json.dumps(choices.choices(OUT)))
    assert val_choices.OUT == OUT and val_choices.main(["--check"]) == 0
    sweeps = choices.sweep_files(OUT)
    for sweep in sweeps:                                     # seeds no table uses
        seeds = {s for runs in json.loads(sweep.read_text()).values() for s in runs}
        assert seeds and all(int(s) >= 100 for s in seeds), (sweep.name, seeds)
    assert {"dropout.json", "il.json", "optim.json"} <= {p.name for p in sweeps}
    tpn = [json.loads(p.read_text()) for p in OUT.glob("tpn_placement_*_tpn*.json")
           if not p.name.count(".lr")]
    assert all(d["split"] == "val" for d in tpn)


def test_defaults_are_the_choices():
    from orgnav_jax import train as train_cli
    from orgnav_jax.tpn.config import TPN_LR, TestTime, TPNConfig
    from orgnav_jax.training.config import TABLE_DROPOUT, TrainConfig, get_config
    chosen = {k: v["value"] for k, v in choices.choices(OUT).items()}
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
        assert all(float(Row.of(row).lr) == chosen["tpn_lr"]
                   for row in spec["rows"] if Row.of(row).is_tpn)
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


def test_a_truncated_sweep_or_an_unknown_option_is_one_line_and_writes_nothing(
        val_choices, tmp_path, monkeypatch, capsys):
    """Issue 55: val_choices.py ended in a traceback on a truncated sweep file and ran
    (rewriting its record) whatever options it was given: a sweep file is read through
    its typed reader (one line naming the file and field, exit 2) before anything is
    written; an unknown option is argparse's usage and exit 2."""
    from orgnav_jax.errors import run_cli
    monkeypatch.setattr(val_choices, "OUT", tmp_path)
    record = {"d0": {"100": {"success": 0.6, "spl": 0.3, "env_steps": 1, "row": "baseline",
                             "overrides": {"dropout": 0.0}}}}
    text = json.dumps(record)
    tpn = {"tpn_dir": "r", "split": "val", "scope": "all",
           "results": {"0.001": {"success": 0.5, "spl": 0.2}}}
    cases = [
        ("dropout.json", text[: len(text) // 2], "dropout.json: not a val sweep JSON"),
        ("dropout.json", json.dumps({"d0": {"100": {**record["d0"]["100"],
                                                    "success": "high"}}}),
         "dropout.json: 'd0' seed '100': field 'success': expected a finite number"),
        ("dropout.json", json.dumps({"d0": {"s100": record["d0"]["100"]}}),
         "'d0' seed 's100': expected an integer seed"),
        ("dropout.json", json.dumps({"d0": []}), "variant 'd0': expected an object"),
        ("savn.json", json.dumps({"d0": {"100": {"success": 0.5, "spl": 0.1,
                                                  "row": "dsavn"}}}),
         "field 'overrides': expected a JSON object, got null"),
        ("tpn_placement_baseline-ours-s100_tpn.json",
         json.dumps({**tpn, "results": {"fast": tpn["results"]["0.001"]}}),
         "results['fast']: expected a learning rate as the key"),
    ]
    for name, content, message in cases:
        for path in tmp_path.iterdir():
            path.unlink()
        if name == "savn.json":
            (tmp_path / "dropout.json").write_text(text)
        if name.startswith("tpn_placement"):
            for run in choices.TPN_RUNS:
                (tmp_path / f"tpn_placement_baseline-ours-s100_{run}.json").write_text(
                    json.dumps(tpn))
        (tmp_path / name).write_text(content)
        before = sorted(p.name for p in tmp_path.iterdir())
        assert run_cli(val_choices.main, []) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], (name, err)
        assert sorted(p.name for p in tmp_path.iterdir()) == before     # nothing written
    with pytest.raises(SystemExit) as exit_:
        val_choices.main(["--out", str(tmp_path)])
    assert exit_.value.code == 2 and "unrecognized arguments: --out" in capsys.readouterr().err
