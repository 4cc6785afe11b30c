"""A table extended to convergence (orgnav_jax/tables/extend.py; run_table.py with a
spec's "extends"), on a hand-made base table: val curves written as metrics, test results
from per-episode flags, checkpoints as placeholder files. The training itself is the
trainer's stop criterion (test_convergence.py); here it is a recorded call. No learning
test."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers import experiment_script, fake_results

from orgnav_jax import api
from orgnav_jax.tables import extend

STEP = 204_800
ROWS = ["random", "baseline", "il", "org", "savn", "baseline+tpn@1e-4", "il+tpn@1e-4"]


def write_run(run: Path, success: list[float], first_step: int = STEP, tested: bool = True,
              rng=np.random.default_rng(0)) -> None:
    """A run directory: val success every STEP env steps (from first_step), a checkpoint
    placeholder at the last of them, and when `tested` its test results, evaluation
    episodes and a TPN's."""
    run.mkdir(parents=True)
    records = [{"kind": "val", "env_steps": first_step + i * STEP, "episodes": 1000,
                "success": s} for i, s in enumerate(success)]
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    last = run / "checkpoints" / str(records[-1]["env_steps"])
    last.mkdir(parents=True)
    (last / "state").write_text("weights")
    if tested:
        results = json.dumps(fake_results(rng.random(40) < 0.5, rng))
        (run / "test_results.json").write_text(results)
        (run / "episodes-calibrated-test-seed0.json").write_text("[]")
        (run / "tpn").mkdir()
        (run / "tpn" / "test_tpn@1e-4.json").write_text(results)


@pytest.fixture()
def base(tmp_path) -> Path:
    """Table BASE at 50 evaluations: baseline flat (converged), il rising (not), org's
    seed 1 not tested yet, savn's seeds evaluated at different steps (one per program),
    random tested."""
    out = tmp_path / "base"
    runs = out / "runs"
    for seed in (0, 1):
        write_run(runs / f"baseline-s{seed}", [0.5] * 50)
        write_run(runs / f"il-s{seed}", np.linspace(0.1, 0.6, 50).tolist())
        write_run(runs / f"org-s{seed}", [0.5] * 50, tested=seed == 0)
        write_run(runs / f"savn-s{seed}", [0.5] * 50, first_step=STEP + seed)
        (runs / f"random-s{seed}").mkdir()
        (runs / f"random-s{seed}" / "test_results.json").write_text(
            json.dumps(fake_results(np.arange(40) < 2, np.random.default_rng(seed))))
    (out / "spec.json").write_text(json.dumps(spec_of(out, 50 * STEP)))
    return out


def spec_of(out: Path, total_env_steps: int, **fields) -> dict:
    return {"out": str(out), "seeds": [0, 1], "population": True, "converged": True,
            "tpn": {}, "rows": ROWS, **fields,
            "config": {"eval_episodes_per_room_type": 250, "total_env_steps": total_env_steps}}


def snapshot(top: Path) -> dict[str, bytes]:
    return {str(p.relative_to(top)): p.read_bytes() for p in sorted(top.rglob("*"))
            if p.is_file()}


def test_rows_are_carried_extended_or_left_by_the_rule(base, tmp_path):
    before = snapshot(base)
    out = tmp_path / "ext"
    states = extend.prepare(base, out, ROWS, [0, 1])
    assert {row: s.action for row, s in states.items()} == {
        "random": "carry", "baseline": "carry", "il": "extend", "org": "wait", "savn": "carry"}
    assert states["baseline"].why == f"converged at B' = {40 * STEP:,}"
    assert states["il"].why == f"not converged at {50 * STEP:,} env steps"
    assert states["org"].why == f"seed 1 not tested in {base} yet"
    assert states["savn"].why.startswith("not judged: SAVN trains one seed per program")
    assert states["il"].describe("il", "B") == (
        f"il: trains on from B's runs until the convergence rule holds (not converged at "
        f"{50 * STEP:,} env steps)")
    for seed in (0, 1):           # carried over whole; extended without test results, TPN
        kept = snapshot(base / "runs" / f"baseline-s{seed}")
        assert {k: v for k, v in snapshot(out / "runs" / f"baseline-s{seed}").items()
                if k != "provenance.json"} == kept
        il = snapshot(out / "runs" / f"il-s{seed}")
        assert sorted(il) == [f"checkpoints/{50 * STEP}/state", "metrics.jsonl",
                              "provenance.json"]
        did = json.loads(il["provenance.json"])[-1]["did"]
        assert did == (f"copied from {base}/runs/il-s{seed} without its test results and "
                       "TPN, to train on under the convergence rule")
    assert (out / "runs" / "random-s1" / "test_results.json").exists()
    assert (out / "runs" / "savn-s1" / "test_results.json").exists()
    assert not (out / "runs" / "org-s0").exists()            # waits for its seed 1
    assert snapshot(base) == before                           # the base is only read
    # again: what is already copied is left as it is (a run that trained on is kept)
    (out / "runs" / "il-s0" / "metrics.jsonl").write_text("trained on\n")
    extend.prepare(base, out, ROWS, [0, 1])
    assert (out / "runs" / "il-s0" / "metrics.jsonl").read_text() == "trained on\n"


def test_a_row_to_extend_waits_for_the_checkpoint_it_trains_on_from(base, tmp_path):
    """A checkout without BASE's checkpoints: a row not converged is left (training on
    from step 0 would be another experiment), nothing copied; once its runs are in OUT,
    BASE's checkpoints are not needed."""
    out = tmp_path / "ext"
    lost = base / "runs" / "il-s1" / "checkpoints"
    (lost / str(50 * STEP)).rename(lost / f"{50 * STEP}.orbax-checkpoint-tmp-1")  # unfinished
    state = extend.prepare(base, out, ROWS, [0, 1])["il"]
    assert state == extend.RowState("wait", f"not converged at {50 * STEP:,} env steps, but "
                                            f"{lost} has no checkpoint of that step to "
                                            f"train on from (newest: none); restore it")
    assert not (out / "runs" / "il-s0").exists()
    (lost / "2048").mkdir()
    assert "(newest: 2,048)" in extend.row_state(base, "il", [0, 1], out).why
    for seed in (0, 1):
        extend.copy_row(base, out, "il", [seed], carry=False)
    assert extend.row_state(base, "il", [0, 1], out).action == "extend"


def test_an_extended_run_without_checkpoints_is_not_trained_again_from_zero(
        base, tmp_path, monkeypatch, cli_error):
    """Its copy in OUT lost its checkpoints (a new checkout): a one-line error, exit 2,
    nothing trained."""
    run_table = experiment_script("run_table")
    monkeypatch.setattr(api, "train_seeds", lambda *a, **k: pytest.fail("trained"))
    out = tmp_path / "ext"
    extend.prepare(base, out, ROWS, [0, 1])
    shutil.rmtree(out / "runs" / "il-s1" / "checkpoints")
    spec_path = tmp_path / "ext.json"
    spec_path.write_text(json.dumps(spec_of(out, 100 * STEP, extends=str(base))))
    line = cli_error(run_table.main, ["--spec", spec_path])
    assert line == (f"error: {out}/runs/il-s1: no checkpoint to train on from (the extended "
                    f"table continues its runs); restore its checkpoints, or remove the run "
                    f"directory to copy it again from the base table"), line


def test_ctrl_c_leaves_each_run_s_metrics_at_its_newest_checkpoint(base, tmp_path,
                                                                   monkeypatch, capsys):
    """Interrupted while a row trains on: every run's metrics.jsonl is cut back to the step
    of its newest checkpoint (what the rerun keeps), the records before it unchanged, and
    the interrupt goes on (exit 130 from the command line)."""
    run_table = experiment_script("run_table")
    out = tmp_path / "ext"

    def train_seeds(cfg, seeds, **kw):
        for seed in seeds:
            run = out / "runs" / f"il-s{seed}"
            with (run / "metrics.jsonl").open("a") as f:
                for i in (51, 52, 53):
                    f.write(json.dumps({"kind": "val", "env_steps": i * STEP,
                                        "success": 0.6}) + "\n")
                f.write('{"kind": "tra')                    # a line cut by the interrupt
            (run / "checkpoints" / str(52 * STEP)).mkdir()
            (run / "checkpoints" / f"{53 * STEP}.orbax-checkpoint-tmp-7").mkdir()
        raise KeyboardInterrupt

    monkeypatch.setattr(api, "train_seeds", train_seeds)
    spec_path = tmp_path / "ext.json"
    spec_path.write_text(json.dumps(spec_of(out, 100 * STEP, extends=str(base))))
    assert run_table.run_cli(run_table.main, ["--spec", str(spec_path)]) == 130
    for seed in (0, 1):
        kept = (out / "runs" / f"il-s{seed}" / "metrics.jsonl").read_text().splitlines()
        base_lines = (base / "runs" / f"il-s{seed}" / "metrics.jsonl").read_text().splitlines()
        assert kept[:50] == base_lines
        assert [json.loads(line)["env_steps"] for line in kept[50:]] == [51 * STEP, 52 * STEP]
        records = json.loads((out / "runs" / f"il-s{seed}" / "provenance.json").read_text())
        assert records[-1]["did"] == f"trained to env step {52 * STEP:,}, interrupted"
    err = capsys.readouterr().err
    assert (f"interrupted: {out / 'runs' / 'il-s1'}/metrics.jsonl kept to env step "
            f"{52 * STEP:,}, its newest checkpoint (1 later records dropped)") in err


def test_run_table_extends_only_the_rows_not_converged(base, tmp_path, monkeypatch, capsys):
    """The base's converged rows keep their results; the one not converged trains on in
    one program under the rule (resumed, to the spec's cap) and is tested again, its TPN
    trained again; the row the base has not finished is left out."""
    run_table = experiment_script("run_table")
    calls = []

    def test_run(where, progress=False):
        doc = fake_results(np.arange(40) < 30, np.random.default_rng(3))
        (Path(where) / "test_results.json").write_text(json.dumps(doc))
        return doc

    def evaluate_run(where, split, out, **kw):
        calls.append(("tpn test", Path(where).parent.name, kw))
        doc = fake_results(np.arange(40) < 32, np.random.default_rng(4))
        Path(out).parent.mkdir(exist_ok=True)          # (train_tpn, recorded, makes it)
        Path(out).write_text(json.dumps(doc))
        return doc

    chunks_run = 3

    def train_seeds(cfg, seeds, **kw):
        calls.append(("train_seeds", Path(cfg.run_dir).name, cfg.total_env_steps,
                      list(seeds), kw))
        return [{"chunks_run": chunks_run} for _ in seeds]

    monkeypatch.setattr(api, "train_seeds", train_seeds)
    monkeypatch.setattr(api, "train", lambda *a, **k: pytest.fail("trained one by one"))
    monkeypatch.setattr(api, "test_run", test_run)
    monkeypatch.setattr(api, "train_tpn", lambda cfg, **kw: calls.append(
        ("train_tpn", Path(cfg.base_dir).name)))
    monkeypatch.setattr(api, "evaluate_run", evaluate_run)
    out = tmp_path / "ext"
    spec_path = tmp_path / "ext.json"
    spec_path.write_text(json.dumps(spec_of(out, 100 * STEP, extends=str(base))))
    run_table.main(["--spec", str(spec_path)])
    assert calls[0] == ("train_seeds", "il", 100 * STEP, [0, 1],
                        {"resume": True, "progress": False, "until_converged": True})
    assert [c[:2] for c in calls[1:]] == [("train_tpn", "il-s0"), ("tpn test", "il-s0"),
                                          ("train_tpn", "il-s1"), ("tpn test", "il-s1")]
    printed = capsys.readouterr().out
    assert f"org: left for a later run (seed 1 not tested in {base} yet)" in printed
    results = json.loads((out / "results.json").read_text())
    assert set(results) == set(ROWS) - {"org"}
    base_baseline = json.loads((base / "runs" / "baseline-s0" / "test_results.json")
                               .read_text())["overall"]
    assert results["baseline"]["0"]["success"] == base_baseline["success"]
    assert results["il"]["1"]["success"] == pytest.approx(0.75)
    assert json.loads((out / "spec.json").read_text())["extends"] == str(base)
    page = (out / "convergence.md").read_text()
    assert f"This table extends `{base}`" in page and f"to at most {100 * STEP:,} env" in page
    assert "| il | 0, 1 | 50 |" in page
    did = [r["did"] for r in json.loads((out / "runs" / "il-s1" / "provenance.json")
                                         .read_text())]
    assert did.count("trained on under the convergence rule in one program with seeds "
                     "0 1") == 1
    # killed after training, before its tests: the rerun trains nothing, records nothing
    chunks_run = 0
    for seed in (0, 1):
        (out / "runs" / f"il-s{seed}" / "test_results.json").unlink()
    first_run_calls = len(calls)
    run_table.main(["--spec", str(spec_path)])
    assert [c[:2] for c in calls[first_run_calls:]] == [("train_seeds", "il")]  # TPNs kept
    did = [r["did"] for r in json.loads((out / "runs" / "il-s1" / "provenance.json")
                                         .read_text())]
    assert did.count("trained on under the convergence rule in one program with seeds "
                     "0 1") == 1


@pytest.mark.parametrize("change, message", [
    ({"converged": False}, "field 'converged': \"extends\" trains rows on under the "
                           "convergence rule"),
    ({"seeds": [0, 1, 2]}, "field 'seeds': [0, 1, 2] differs from"),
    ({"rows": ["baseline", "org_il"]}, "field 'rows': org_il is not a row of"),
    ({"tpn": {"total_episodes": 10}}, "field 'tpn':"),
    ({"config": {"eval_episodes_per_room_type": 250, "total_env_steps": 100 * STEP,
                 "dropout": 0.5}}, "field 'config': dropout 0.5 differs from"),
    ({"config": {"eval_episodes_per_room_type": 250, "total_env_steps": 50 * STEP}},
     f"field 'config': total_env_steps {50 * STEP} is the cap of the extended rows: "
     f"expected more than"),
    ({"extends": "nowhere"}, "field 'extends': nowhere/spec.json missing"),
    ({"out": "BASE"}, "is the table's own out"),
])
def test_bad_extends_specs_are_one_line_errors_and_write_nothing(base, tmp_path, cli_error,
                                                                 change, message):
    out = tmp_path / "ext"
    spec = {**spec_of(out, 100 * STEP, extends=str(base)), **change}
    if spec["out"] == "BASE":
        spec["out"] = str(base)
    spec_path = tmp_path / "ext.json"
    spec_path.write_text(json.dumps(spec))
    before = snapshot(base)
    line = cli_error(experiment_script("run_table").main, ["--spec", spec_path])
    assert f"table spec {spec_path}: " in line and message in line, line
    assert not out.exists() and snapshot(base) == before
