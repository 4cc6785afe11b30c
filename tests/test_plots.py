"""Learning curves (python -m orgnav_jax.plots curves): reading metrics.jsonl, the mean and
band over seeds, the PNG, the summary and one-line errors for bad inputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orgnav_jax import plots

# val success / spl at env steps 100, 200, 300 of two rows x two seeds
VAL = {"baseline-s0": ([0.1, 0.3, 0.2], [0.05, 0.1, 0.1]),
       "baseline-s1": ([0.3, 0.5, 0.4], [0.15, 0.2, 0.3]),
       "il-s0": ([0.0, 0.2, 0.6], [0.0, 0.1, 0.3]),
       "il-s1": ([0.2, 0.2, 0.4], [0.1, 0.1, 0.1])}
STEPS = [100, 200, 300]


def write_run(run_dir, success, spl, steps=STEPS, extra=()):
    """metrics.jsonl as training/loop.py's MetricsLog writes it: train records between
    val records; `extra` lines are appended as they are."""
    run_dir.mkdir(parents=True, exist_ok=True)
    lines = []
    for t, su, sp in zip(steps, success, spl):
        lines.append({"kind": "train", "env_steps": t, "success": 0.9, "loss": 1.0})
        lines.append({"kind": "val", "env_steps": t, "episodes": 80, "success": su,
                      "spl": sp, "success_L5": su, "spl_L5": sp})
    text = "".join(json.dumps(r) + "\n" for r in lines) + "".join(extra)
    (run_dir / "metrics.jsonl").write_text(text)
    return run_dir


@pytest.fixture
def runs(tmp_path):
    return [write_run(tmp_path / "runs" / name, *vals) for name, vals in VAL.items()]


def test_aggregate_mean_and_band_over_seeds_at_common_steps():
    a = plots.aggregate([(np.array([100, 200, 300]), np.array([0.1, 0.3, 0.2])),
                         (np.array([300, 100, 200]), np.array([0.4, 0.3, 0.5]))])
    np.testing.assert_array_equal(a["env_steps"], [100, 200, 300])
    np.testing.assert_allclose(a["mean"], [0.2, 0.4, 0.3])
    np.testing.assert_allclose(a["min"], [0.1, 0.3, 0.2])
    np.testing.assert_allclose(a["max"], [0.3, 0.5, 0.4])
    np.testing.assert_allclose(a["std"], [0.1, 0.1, 0.1])
    assert a["seeds"] == 2 and a["dropped"] == 0
    # different grids: only the shared steps, and how many values were left out
    b = plots.aggregate([(np.array([100, 200, 300]), np.array([1.0, 2.0, 3.0])),
                         (np.array([100, 300]), np.array([3.0, 5.0]))])
    np.testing.assert_array_equal(b["env_steps"], [100, 300])
    np.testing.assert_allclose(b["mean"], [2.0, 4.0])
    assert b["dropped"] == 1
    with pytest.raises(plots.CurveError, match="share no val env step"):
        plots.aggregate([(np.array([100]), np.array([1.0])), (np.array([200]), np.array([1.0]))])


def test_runs_are_grouped_into_rows_by_name_without_seed_suffix(tmp_path):
    rows = plots.group_runs(["runs/baseline-s0", "runs/baseline-s1/", "x/il-s12",
                             "mine=runs/other", "runs/plain"])
    assert list(rows) == ["baseline", "il", "mine", "plain"]
    assert [p.name for p in rows["baseline"]] == ["baseline-s0", "baseline-s1"]
    assert rows["mine"][0].name == "other"


def test_plot_curves_writes_png_and_returns_the_aggregates(runs, tmp_path, capsys):
    out = tmp_path / "curves.png"
    data = plots.plot_curves(runs, out)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 5000
    assert list(data) == ["baseline", "il"]
    np.testing.assert_allclose(data["baseline"]["success"]["mean"], [0.2, 0.4, 0.3])
    np.testing.assert_allclose(data["il"]["success"]["min"], [0.0, 0.2, 0.4])
    np.testing.assert_allclose(data["il"]["success"]["max"], [0.2, 0.2, 0.6])
    np.testing.assert_allclose(data["il"]["spl"]["mean"], [0.05, 0.1, 0.2])
    assert data["baseline"]["best"] == pytest.approx(0.4)   # mean of 0.3 and 0.5
    assert data["il"]["best"] == pytest.approx(0.5)         # mean of 0.6 and 0.4
    summary = capsys.readouterr().out.splitlines()
    assert summary[1].split() == ["baseline", "2", "3", "300", "30.0", "40.0"]
    assert summary[2].split() == ["il", "2", "3", "300", "50.0", "50.0"]


def test_curves_cli_default_out_options_and_resumed_runs(runs, tmp_path, capsys):
    # a resumed run logged step 300 again: the later record wins
    again = json.dumps({"kind": "val", "env_steps": 300, "success": 0.8, "spl": 0.4}) + "\n"
    write_run(tmp_path / "runs" / "il-s1", *VAL["il-s1"], extra=[again])
    assert plots.main(["curves", *map(str, runs), "--band", "std"]) == 0
    out = runs[0] / "curves.png"                        # the first run directory
    assert out.stat().st_size > 5000
    text = capsys.readouterr().out
    assert f"wrote {out}" in text
    assert text.splitlines()[2].split()[4] == "70.0"          # il final: (0.6 + 0.8) / 2
    mine = tmp_path / "one.png"
    assert plots.main(["curves", f"B={runs[0]}", "--metrics", "success_L5",
                       "--out", str(mine)]) == 0
    assert mine.stat().st_size > 0 and "B " in capsys.readouterr().out


def test_curves_note_when_seeds_have_different_step_grids(tmp_path, capsys):
    a = write_run(tmp_path / "r-s0", [0.1, 0.2, 0.3], [0.0] * 3)
    b = write_run(tmp_path / "r-s1", [0.3, 0.4], [0.0] * 2, steps=[100, 200])
    data = plots.plot_curves([a, b], tmp_path / "c.png")
    np.testing.assert_array_equal(data["r"]["success"]["env_steps"], [100, 200])
    assert "val steps differ" in capsys.readouterr().err


@pytest.mark.parametrize("case, message", [
    ("missing_dir", "no such run directory"),
    ("missing_file", "metrics.jsonl: missing"),
    ("empty_file", "metrics.jsonl: empty"),
    ("no_val", "metrics.jsonl: no val records"),
    ("bad_json", "metrics.jsonl line 3: not valid JSON"),
    ("no_metric", "metrics.jsonl: the val record at env step 100 has no numeric 'timeout'"),
    ("disjoint_grids", "row 'r' .*share no val env step"),
])
def test_curves_cli_bad_inputs_are_one_line_errors(tmp_path, capsys, case, message):
    run = tmp_path / "r-s0"
    args = [str(run)]
    if case == "missing_file":
        run.mkdir()
    elif case == "empty_file":
        run.mkdir()
        (run / "metrics.jsonl").write_text("\n")
    elif case == "no_val":
        run.mkdir()
        (run / "metrics.jsonl").write_text(json.dumps({"kind": "train", "env_steps": 1}) + "\n")
    elif case == "bad_json":
        write_run(run, [0.1], [0.1], steps=[100], extra=["{oops\n"])
    elif case == "no_metric":
        write_run(run, [0.1], [0.1], steps=[100])
        args += ["--metrics", "success", "timeout"]
    elif case == "disjoint_grids":
        write_run(run, [0.1], [0.1], steps=[100])
        args.append(str(write_run(tmp_path / "r-s1", [0.1], [0.1], steps=[200])))
    assert plots.main(["curves", *args, "--out", str(tmp_path / "c.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ")
    assert str(run) in err
    import re
    assert re.search(message, err)
    assert not (tmp_path / "c.png").exists()


def test_run_table_writes_curves_of_non_tpn_rows_and_never_fails(tmp_path, capsys):
    from helpers import experiment_script
    run_table = experiment_script("run_table")
    results = {"baseline": {"0": {}, "1": {}}, "baseline+tpn": {"0": {}}, "il": {"0": {}}}
    assert run_table.write_curves(tmp_path, results) is None     # no metrics.jsonl yet
    for name in ("baseline-s0", "baseline-s1"):
        write_run(tmp_path / "runs" / name, *VAL[name])
    out = run_table.write_curves(tmp_path, results)              # il-s0 has no log: left out
    assert out == tmp_path / "curves.png" and out.stat().st_size > 5000
    (tmp_path / "runs" / "il-s0").mkdir()
    (tmp_path / "runs" / "il-s0" / "metrics.jsonl").write_text("{oops\n")
    out.unlink()
    assert run_table.write_curves(tmp_path, results) is None     # a warning, not an error
    assert "warning: no learning curves" in capsys.readouterr().err
    assert not out.exists()


def test_a_run_given_twice_is_not_two_seeds(tmp_path, cli_error):
    """Issue 38: `plots curves RUN RUN` (or the same run spelled two ways) is one line,
    not a row of two seeds; nothing is written."""
    from orgnav_jax.plots.cli import main
    run = tmp_path / "run"
    run.mkdir()
    for argv in (["curves", run, run], ["curves", run, f"{tmp_path}/./run"],
                 ["curves", f"a={run}", f"b={run}"]):
        assert "given twice" in cli_error(main, argv)
    assert list(run.iterdir()) == []
