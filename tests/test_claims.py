"""The tables library (orgnav_jax/tables): paired statistics, verdicts, the claims and
--check on a hand-made table; and the experiments/ command lines over it (claims.py,
run_table.py, the sweeps, the pages of the superseded investigations)."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import EXPERIMENTS, experiment_script, fake_results

from orgnav_jax.tables import (adjacency, before_parity, layout, provenance, rows, runs, spec,
                               stats, table_files)
from orgnav_jax.tables import claims as claims_lib

BEFORE_PARITY = EXPERIMENTS / "results" / "before_parity"


@pytest.fixture(scope="module")
def claims():
    """experiments/claims.py, the command line."""
    return experiment_script("claims")


@pytest.fixture()
def table_dir(tmp_path):
    """Rows baseline, il (better in every seed), org (better on average in 2 of 3 seeds),
    random (worse), 3 seeds, 200 episodes each, as run_table.py lays them out."""
    rng = np.random.default_rng(1)
    rates = {"random": [0.05, 0.05, 0.05], "baseline": [0.5, 0.6, 0.4],
             "il": [0.6, 0.7, 0.5], "org": [0.65, 0.7, 0.35]}
    for row, by_seed in rates.items():
        for seed, p in enumerate(by_seed):
            success = np.zeros(200, bool)
            success[rng.permutation(200)[:int(p * 200)]] = True
            run = tmp_path / "runs" / f"{row}-s{seed}"
            run.mkdir(parents=True)
            (run / "test_results.json").write_text(json.dumps(fake_results(success, rng)))
    spec = {"out": str(tmp_path), "rows": ["baseline", "il", "org", "random",
                                           "org_il+tpn@1e-3"],
            "seeds": [0, 1, 2], "config": {}, "tpn": {}}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    return tmp_path


def test_statistics_verdicts_and_intervals():
    from scipy import stats as sp
    d = np.array([10.5, -3.0, -2.5])
    st = stats.statistics(d, 1)
    assert st["verdict"] == "holds on average (1 of 3 seeds)"
    assert st["std"] == pytest.approx(d.std(ddof=1))            # the sample std
    half = sp.t.ppf(0.975, 2) * d.std(ddof=1) / np.sqrt(3)
    assert st["interval"] == pytest.approx((d.mean() - half, d.mean() + half))
    assert st["p"] == pytest.approx(sp.ttest_1samp(d, 0, alternative="greater").pvalue)
    assert not st["excludes_0"]
    assert stats.statistics(np.array([2.0, 3.0, 2.5]), 1)["verdict"] == "holds in every seed"
    assert stats.statistics(np.array([2.0, 3.0, 2.5]), 1)["excludes_0"]
    assert stats.statistics(np.array([2.0, 3.0, 2.5]), -1)["verdict"] == "does not hold"
    assert stats.statistics(np.array([-2.0, -3.0]), -1)["verdict"] == "holds in every seed"
    # one seed: no spread, no interval, no test; the spread of a table is the sample std
    one = stats.statistics(np.array([1.5]), 1)
    assert one["std"] is None and one["interval"] is None and one["p"] is None
    assert stats.mean_std([1.0, 2.0, 4.0]) == f"2.3 ± {np.std([1.0, 2.0, 4.0], ddof=1):.1f}"
    assert stats.mean_std([3.0]) == "3.0 ± 0.0"


def test_a_row_name_is_taken_apart_once():
    from orgnav_jax.train import PRETRAIN_PIPELINES
    row = rows.parse_row("org_il+tpn_all@1e-4")
    assert (row.base, row.variant, row.lr, row.is_tpn) == ("org_il", "tpn_all", "1e-4", True)
    assert row.name == "org_il+tpn_all@1e-4" and row.tpn_tag == "tpn_all@1e-4"
    assert row.test_time() == {"when": "all", "tpn_lr": 1e-4}
    assert rows.parse_row("baseline+tpn").test_time() == {}
    assert rows.parse_row("random") == rows.Row("random")
    for bad, match in (("baseline@1e-3", "unknown row"), ("nope", "unknown row"),
                       ("random+tpn", "unknown row"), ("org+tpn@fast", "unknown row"),
                       ("org+tpn@-1", "unknown row"), ("dsavn+tpn", "cannot be a TPN base")):
        with pytest.raises(ValueError, match=match):
            rows.parse_row(bad)
    assert rows.lr_tag(["baseline", "org+tpn@1e-4", "org+tpn_all@1e-2"]) == "1e-4"
    assert rows.lr_tag(["baseline"]) == "1e-3"
    assert rows.PRETRAIN_ROWS == PRETRAIN_PIPELINES       # the training CLI's list
    assert layout.results_path(Path("T"), "org_il+tpn_all@1e-3", 3) == \
        Path("T/runs/org_il-s3/tpn/test_tpn_all@1e-3.json")
    assert layout.results_path(Path("T"), "vtnet", 0) == \
        Path("T/runs/vtnet-s0/test_results.json")


def test_predictions_are_claims_of_calibrated_tables_only():
    spec = lambda preset, rows: {"rows": rows, "config": {"scene_preset": preset}}
    names = lambda s: [c[0] for c in claims_lib.claims("1e-4", s)]
    calibrated = names(spec("calibrated", ["baseline", "we", "dsp"]))
    assert "full model > Baseline (paper +12.9)" in calibrated and "D-SP > WE" in calibrated
    assert ("org_il+tpn@1e-4", "baseline") in [c[1:3] for c in claims_lib.claims(
        "1e-4", spec("calibrated", ["baseline"]))]
    assert names(spec("calibrated_22m", ["baseline", "we", "dsp"])) == calibrated
    for other in (spec("small", ["baseline", "we", "dsp"]), None):
        assert not {"full model > Baseline (paper +12.9)", "D-SP > WE"} & set(names(other))


def test_claims_table_check_and_tampering(claims, table_dir, capsys):
    assert claims.main([str(table_dir)]) == 0
    text = (table_dir / "claims.md").read_text()
    line = next(x for x in text.splitlines() if x.startswith("| IL > Baseline |"))
    assert "| 0,1,2 | +10.0 " in line and "holds in every seed, interval excludes 0" in line
    line = next(x for x in text.splitlines() if x.startswith("| ORG > Baseline |"))
    assert "holds on average (2 of 3 seeds)" in line
    assert "| Baseline > Random |" in text and "| ORG + IL > ORG | not measured |" in text
    assert "not measured yet" in text                   # no full-model row
    capsys.readouterr()
    assert claims.main([str(table_dir), "--compact"]) == 0
    short = capsys.readouterr().out
    assert "| IL > Baseline | 3 | +10.0 [" in short and "ORG + IL > ORG" not in short
    # the bootstrap interval: over seeds and episodes, around the mean difference
    _, results, episodes = runs.read_table_dir(table_dir)
    lo, hi = stats.bootstrap_interval(episodes, "il", "baseline", ["0", "1", "2"],
                                      "success")
    assert lo < 10.0 < hi and hi - lo < 20
    # --check agrees, then fails on an edited table and on a tampered run
    assert claims.main(["--check", str(table_dir)]) == 0
    table = table_dir / "table.md"
    table.write_text(table.read_text().replace("| il | 3 |", "| il | 4 |"))
    assert claims.main(["--check", str(table_dir)]) == 1
    assert "table.md: differs" in capsys.readouterr().err
    claims.main([str(table_dir)])
    run = table_dir / "runs" / "il-s1" / "test_results.json"
    doc = json.loads(run.read_text())
    doc["overall"]["success"] += 0.01
    run.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"il-s1/test_results.json: the stored summary "
                                         r"differs from its per-episode outcomes in "
                                         r"\['success'\]"):
        claims.main(["--check", str(table_dir)])


def test_before_after_lists_claims_of_both_tables_and_changed_verdicts(claims, table_dir,
                                                                          tmp_path_factory,
                                                                          capsys):
    """--before: a line per claim measured in both tables; a changed verdict level is
    marked, an unchanged one is not."""
    after = tmp_path_factory.mktemp("after")
    shutil.copytree(table_dir, after, dirs_exist_ok=True)
    rng = np.random.default_rng(2)
    for seed, p in enumerate([0.45, 0.55, 0.35]):           # IL now below the Baseline
        success = np.zeros(200, bool)
        success[rng.permutation(200)[:int(p * 200)]] = True
        (after / "runs" / f"il-s{seed}" / "test_results.json").write_text(
            json.dumps(fake_results(success, rng)))
    assert claims.main([str(after), "--before", str(table_dir)]) == 0
    lines = capsys.readouterr().out.splitlines()
    il = next(x for x in lines if x.startswith("- IL > Baseline: "))
    assert "+10.0 [" in il and "holds in every seed (3 seeds) -> -5.0 [" in il, il
    assert il.endswith("does not hold (3 seeds); **verdict changed**"), il
    org = next(x for x in lines if x.startswith("- ORG > Baseline: "))
    assert "verdict changed" not in org and org.count("holds on average (2 of 3 seeds)") == 2
    assert not any("ORG + IL > ORG" in x for x in lines)    # measured in neither


def test_provenance_table_is_generated_from_the_runs_records(claims, table_dir, capsys):
    """provenance.md: a line per run group and distinct record (code, uncommitted
    changes, device, CPU, jax), its seeds as ranges, what the processes did; runs without
    records say so. --check compares it where it exists and skips it where a table has
    none (tables made before it)."""
    record = {"code": "a" * 40, "uncommitted_changes": False, "cpu": "Test CPU",
              "device": "cpu cpu", "jax": "0.10.2", "python": "3.11.7",
              "time": "2026-12-04T10:00:00+00:00", "started": "2026-12-04T09:00:00+00:00"}
    for seed in range(3):
        (table_dir / "runs" / f"baseline-s{seed}" / "provenance.json").write_text(json.dumps(
            [dict(record, did="trained in one program with seeds 0 1 2"),
             dict(record, did="resumed and finished, tested")]))
    (table_dir / "runs" / "il-s2" / "provenance.json").write_text(json.dumps(
        [dict(record, code="b" * 40, device="gpu NVIDIA H200", did="trained, tested")]))
    assert claims.main(["--check", str(table_dir)]) == 1      # claims.md etc. not written
    assert claims.main([str(table_dir)]) == 0
    text = (table_dir / "provenance.md").read_text()
    lines = text.splitlines()
    assert ("| baseline | 0-2 | trained in one program with seeds 0 1 2; resumed and "
            "finished; tested | aaaaaaa | no | cpu cpu | Test CPU | 0.10.2 | 2026-12-04 |"
            in lines), text
    assert "| il | 2 | trained; tested | bbbbbbb | no | gpu NVIDIA H200 |" in text
    assert "| il | 0-1 | no provenance.json | - | - |" in text
    assert provenance.seed_ranges(["0", "1", "2", "4", "6", "7"]) == "0-2, 4, 6-7"
    capsys.readouterr()
    assert claims.main(["--check", str(table_dir)]) == 0
    assert "provenance.md agree" in capsys.readouterr().out
    (table_dir / "runs" / "il-s2" / "provenance.json").write_text(json.dumps(
        [dict(record, did="trained, tested")]))
    assert claims.main(["--check", str(table_dir)]) == 1
    assert "provenance.md: differs" in capsys.readouterr().err
    (table_dir / "provenance.md").unlink()                   # optional: a table without it
    assert claims.main(["--check", str(table_dir)]) == 0


def test_per_category_groups_and_table(table_dir):
    groups = claims_lib.category_groups()
    assert "Toaster" in groups["anchored"] and "Laptop" in groups["anchored"]
    assert "StoveBurner" in groups["anchors"] and "Television" in groups["anchors"]
    assert "Fridge" in groups["others"]
    assert sorted(sum(groups.values(), [])) == sorted(__import__(
        "orgnav_jax.constants", fromlist=["CATEGORIES"]).CATEGORIES)
    text = claims_lib.per_category(table_dir, "il", "baseline")
    assert "| anchored | **all anchored** |" in text and "| others | Fridge |" in text
    # the groups' rates are over the episodes of their categories: all groups together
    # give the overall difference (+10 points in every seed for il vs baseline)
    assert "il vs baseline, test success (points) paired over seeds 0,1,2" in text


def test_run_table_spec_is_checked(tmp_path):
    good = spec.read_spec(EXPERIMENTS / "tables" / "table_5m.json")
    assert good["seeds"] == [0, 1, 2, 3, 4] and "random" in good["rows"]
    for change, match in (({"rows": ["nope"]}, "field 'rows': unknown row 'nope'"),
                          ({"seeds": [-1]}, "field 'seeds'"),
                          ({"config": {"lr": -1.0}}, "'lr'"),
                          ({"extra": 1}, r"unknown field\(s\) \['extra'\]"),
                          ({"population": "yes"}, "field 'population' is not a bool")):
        bad = tmp_path / "spec.json"
        bad.write_text(json.dumps(dict(good, **change)))
        with pytest.raises(ValueError, match=match):
            spec.read_spec(bad)
    # "converged": true needs what the convergence rule judges
    judged = dict(good, converged=True, config=dict(good["config"],
                                                    eval_episodes_per_room_type=250))
    ok = tmp_path / "judged.json"
    ok.write_text(json.dumps(judged))
    assert spec.read_spec(ok)["converged"] is True
    for change, match in (
            ({"converged": "yes"}, "field 'converged' is not a bool"),
            ({"population": False}, "field 'population': \"converged\": true .* needs the "
                                    "seeds of a row trained in one program"),
            ({"seeds": [0]}, "field 'seeds': \"converged\": true .* needs at least 2 seeds"),
            ({"config": dict(good["config"], eval_episodes_per_room_type=249)},
             "field 'config': eval_episodes_per_room_type 249 gives val evaluations of 996 "
             "episodes; .* at least 1,000"),
            ({"config": good["config"]},             # the default: 50 per room type
             "field 'config': eval_episodes_per_room_type 50 gives")):
        bad = tmp_path / "spec.json"
        bad.write_text(json.dumps(dict(judged, **change)))
        with pytest.raises(ValueError, match=f"table spec {bad}: {match}") as err:
            spec.read_spec(bad)
        assert "\n" not in str(err.value)


def test_provenance_counts_code_changes_not_the_tables_own_files(tmp_path, monkeypatch):
    """A run's provenance says "uncommitted_changes" for edited code, not for the result
    files a running campaign rewrites (experiments/results/) nor for a file mode lost in a
    copy; ORGNAV_CODE names the code of a copy; "device" is what JAX runs on."""
    import subprocess
    git = lambda *a: subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t",
                                     *a], cwd=tmp_path, check=True, capture_output=True)
    for rel in ("orgnav_jax/x.py", "experiments/run.py", "experiments/results/t/table.md"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("a\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "c")
    assert provenance.provenance(tmp_path)["uncommitted_changes"] is False
    (tmp_path / "experiments/results/t/table.md").write_text("b\n")
    assert provenance.provenance(tmp_path)["uncommitted_changes"] is False
    (tmp_path / "experiments/run.py").chmod(0o755)                 # a mode, not code
    assert provenance.provenance(tmp_path)["uncommitted_changes"] is False
    (tmp_path / "experiments/run.py").write_text("b\n")
    p = provenance.provenance(tmp_path)
    assert p["uncommitted_changes"] is True and len(p["code"]) == 40
    assert p["device"].startswith("cpu ")
    monkeypatch.setenv("ORGNAV_CODE", "3c69e07")
    assert provenance.provenance(tmp_path)["code"] == "3c69e07"


def test_committed_tables_agree_with_their_runs():
    """`claims.py --check` on every committed run_table.py output (the tables and the
    knob's points, those made before network parity in results/before_parity too): its
    results.json, table.md and claims.md are what its runs' evidence files give."""
    results = EXPERIMENTS / "results"
    tables = sorted(p.parent for pattern in ("*/spec.json", "before_parity/*/spec.json")
                    for p in results.glob(pattern))
    assert any(t.name.startswith("table_") for t in tables), "no committed table"
    before = {t.name for t in tables if t.parent.name == "before_parity"}
    assert before >= {"table_5m", "table_20m", "knob_p0", "knob_p1", "rerun_org_5m",
                      "rerun_org_il_5m"}, before
    for table in tables:
        assert table_files.check(table) == [], table


def test_the_knob_tables_agree_with_their_runs(tmp_path):
    """experiments/knob.py --check: knob.md is what the knob's runs give (success from
    their test results, adjacency from the matrices in their adjacency.json); a tampered
    matrix is named."""
    knob = experiment_script("knob")
    assert knob.main(["--check"]) == 0
    assert knob.RESULTS == BEFORE_PARITY
    points = before_parity.knob_points(BEFORE_PARITY)
    measured = [r for r in points if r["stats"]]
    assert measured and all(len(r["stats"]["differences"]) == len(r["seeds"]) for r in measured)
    table_runs = before_parity.knob_table_adjacency(BEFORE_PARITY)   # every ORG, ORG + IL run
    assert {row: sorted(r) for row, r in table_runs.items()} == \
        {"org": list("01234"), "org_il": list("01234")}
    adj = next(iter(sorted(BEFORE_PARITY.glob("*/runs/org-s*/adjacency.json"))))
    doc = json.loads(adj.read_text())
    doc["A"][0][1] += 1.0
    bad = tmp_path / "adjacency.json"
    bad.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="adjacency.json: the stored report differs"):
        adjacency.read_adjacency(bad)


def test_tpn_budget_gain_is_paired_by_episode_and_tabled(tmp_path):
    """The TPN budget page (experiments/tpn_budget.py): the gain over the base alone is
    the mean per-episode success difference with its 95% t interval; the table shows the
    chosen lr; --check recomputes the committed sweep's files."""
    from scipy import stats as sp
    rng = np.random.default_rng(0)
    alone = rng.random(400) < 0.6
    better = alone | (rng.random(400) < 0.2)             # never worse, sometimes better
    mean, low, high = before_parity.tpn_budget_gain({"success": better}, {"success": alone})
    d = 100 * (better.astype(float) - alone)
    assert mean == pytest.approx(d.mean()) and low < mean < high and low > 0
    assert high - low == pytest.approx(2 * sp.t.ppf(0.975, 399) * d.std(ddof=1) / np.sqrt(400))
    summary = {"lrs": [1e-3, 1e-2], "bases": {"baseline": {"alone": 0.6, "budgets": {
        "40000": {"val_ce": 1.0, "val_accuracy": 0.5, "success": {"0.001": 0.7, "0.01": 0.65},
                  "chosen": 1e-3, "gain": (mean, low, high)}}}}}
    line = before_parity.tpn_budget_table(summary).splitlines()[2]
    assert line.startswith("| baseline | 40,000 | 1.000 | 50.0 | 60.0 | 70.0 | 65.0 | 0.001 |")
    budget = experiment_script("tpn_budget")
    committed = BEFORE_PARITY / "tpn_budget"                    # the sweep's files
    assert budget.OUT == committed and budget.main(["--check"]) == 0
    copy = tmp_path / "tpn_budget"                             # a tampered summary is named
    shutil.copytree(committed, copy)
    val = copy / "runs" / "baseline-s100" / "val_results.json"
    doc = json.loads(val.read_text())
    doc["overall"]["success"] += 0.01
    val.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="val_results.json: the stored summary differs"):
        budget.main(["--out", str(copy), "--check"])


def test_the_20m_comparison_agrees_with_its_runs(tmp_path):
    """experiments/budget_20m.py --check: budget.md is what the 5 M and 20 M runs' files
    give; the curve points are the first val record at or after each budget, so a changed
    val record at 20 M changes the table."""
    budget = experiment_script("budget_20m")
    assert budget.RESULTS == BEFORE_PARITY and budget.main(["--check"]) == 0
    long = BEFORE_PARITY / before_parity.LONG
    run = long / "runs" / "org-s0"
    vals = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()
            if '"val"' in line]
    assert runs.val_at(run, 20_000_000)["success"] == vals[-1]["success"]
    assert vals[-2]["env_steps"] < 20_000_000 <= vals[-1]["env_steps"]
    copy = tmp_path / "table_20m"
    shutil.copytree(long, copy)
    metrics = copy / "runs" / "org-s0" / "metrics.jsonl"
    lines = metrics.read_text().splitlines()
    last = max(i for i, line in enumerate(lines) if '"val"' in line)
    doc = json.loads(lines[last])
    doc["success"] = 0.0
    lines[last] = json.dumps(doc)
    metrics.write_text("\n".join(lines) + "\n")
    assert before_parity.budget_20m_markdown(BEFORE_PARITY, long_dir=copy) != \
        (long / "budget.md").read_text()
    with pytest.raises(ValueError, match="no val record at or after 30,000,000 env steps"):
        runs.val_at(run, 30_000_000)


# issue 38: the experiment scripts follow the CLIs' error convention (orgnav_jax.errors.
# run_cli: one line naming the file or field, exit 2) and write nothing on bad input

def _snapshot(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.read_bytes() if p.is_file() else None)
            for p in sorted(root.rglob("*")) if not p.is_symlink()}


def test_claims_bad_tables_are_one_line_and_write_nothing(claims, table_dir, tmp_path_factory,
                                                          cli_error):
    missing = tmp_path_factory.mktemp("x") / "nope"
    assert "nope: not a directory" in cli_error(claims.main, [missing])
    # a truncated results file (a kill while it was written) is named
    run = table_dir / "runs" / "il-s1" / "test_results.json"
    text = run.read_text()
    run.write_text(text[: len(text) // 2])
    before = _snapshot(table_dir)
    line = cli_error(claims.main, [table_dir])
    assert "il-s1/test_results.json: not a results JSON" in line, line
    assert _snapshot(table_dir) == before and not (table_dir / "claims.md").exists()
    run.write_text(text)
    # a run folder that is a symbolic link loop is named, not dropped from the table
    loop = table_dir / "runs" / "org-s2"
    shutil.rmtree(loop)
    loop.symlink_to(loop)
    line = cli_error(claims.main, [table_dir])
    assert "org-s2/test_results.json: cannot be read" in line, line
    line = cli_error(claims.main, [table_dir, "--per-category", "org", "baseline"])
    assert "org-s2/test_results.json: cannot be read" in line, line
    loop.unlink()
    # --per-category checks the per-episode outcomes against their summary, as
    # --compact does, and names rows the spec lacks
    doc = json.loads(run.read_text())
    doc["per_episode"]["outcome"][0] = 1 - doc["per_episode"]["outcome"][0]
    run.write_text(json.dumps(doc))
    for argv in ([table_dir, "--per-category", "il", "baseline"], [table_dir, "--compact"]):
        assert "il-s1/test_results.json: the stored summary differs from its per-episode " \
               "outcomes" in cli_error(claims.main, argv)
    assert "--per-category dsp: not a row of" in cli_error(
        claims.main, [table_dir, "--per-category", "dsp", "baseline"])
    assert not (table_dir / "claims.md").exists()


def test_run_table_bad_specs_and_outputs_are_one_line_and_write_nothing(table_dir, tmp_path_factory,
                                                                        cli_error):
    run_table = experiment_script("run_table")
    work = tmp_path_factory.mktemp("specs")
    good = {"out": str(work / "t"), "rows": ["baseline"], "seeds": [0], "config": {},
            "tpn": {}}
    cases = [({"rows": "baseline"}, "field 'rows' missing or not a list"),
             ({"seeds": ["0", "1"]}, "field 'seeds': expected integers >= 0"),
             ({"seeds": [True]}, "field 'seeds': expected integers >= 0"),
             ({"rows": ["baseline", "nope"]}, "field 'rows': unknown row 'nope'"),
             ({"rows": [3]}, "field 'rows': expected row names"),
             ({"rows": []}, "field 'rows': expected at least one row"),
             ({"rows": ["dsavn+tpn"]}, "a SAVN run cannot be a TPN base")]
    for change, message in cases:
        (work / "s.json").write_text(json.dumps(dict(good, **change)))
        assert message in cli_error(run_table.main, ["--spec", work / "s.json"])
    assert "a directory, expected a JSON file" in cli_error(run_table.main, ["--spec", work])
    assert list(work.iterdir()) == [work / "s.json"]           # no output folder made
    # a folder holding the user's own spec.json and table.md is not overwritten
    user = work / "mine"
    user.mkdir()
    (user / "spec.json").write_text("my notes\n")
    (user / "table.md").write_text("| my | table |\n")
    (work / "s.json").write_text(json.dumps(dict(good, out=str(user))))
    line = cli_error(run_table.main, ["--spec", work / "s.json"])
    assert "holds spec.json, table.md that run_table.py did not write" in line, line
    assert {p.name: p.read_text() for p in user.iterdir()} == {
        "spec.json": "my notes\n", "table.md": "| my | table |\n"}
    # a truncated provenance.json is named before any run is trained or evaluated
    prov = table_dir / "runs" / "baseline-s0" / "provenance.json"
    prov.write_text('[{"code": "abc", "ti')
    (work / "s.json").write_text(json.dumps(dict(good, out=str(table_dir))))
    before = _snapshot(table_dir)
    line = cli_error(run_table.main, ["--spec", work / "s.json"])
    assert "baseline-s0/provenance.json: not a provenance JSON" in line, line
    assert _snapshot(table_dir) == before


def test_val_sweep_pretrains_a_vtnet_variant_first_and_reads_a_finished_run(
        tmp_path, monkeypatch):
    """experiments/val_sweep.py: a VTNet variant pre-trains in RUN-pretrain-sS and trains
    from it (as `--preset vtnet` does), another row does not pre-train, and a run whose
    metrics reach the budget (one made elsewhere, without checkpoints) is read, not
    trained again. Training is replaced by a stand-in that writes a run's files."""
    val_sweep = experiment_script("val_sweep")
    from orgnav_jax.training import loop
    from orgnav_jax.training.run_dir import write_config
    calls = []

    def fake_pretrain(cfg, pre, progress=True):
        calls.append(("pretrain", Path(pre).name, Path(cfg.pretrained).name))
        return True

    def fake_train(cfg, resume=False, progress=True):
        calls.append(("train", Path(cfg.run_dir).name, cfg.pretrained and
                      Path(cfg.pretrained).name))
        write_config(cfg.run_dir, cfg)
        Path(cfg.run_dir, "metrics.jsonl").write_text("".join(
            json.dumps({"kind": "val", "env_steps": s, "success": s / 1e5, "spl": 0.1}) + "\n"
            for s in (25600, 51200)))

    monkeypatch.setattr(val_sweep.api, "pretrain_for", fake_pretrain)
    monkeypatch.setattr(loop, "train", fake_train)
    argv = ["--name", "v", "--out", str(tmp_path), "--seeds", "100", "--total-env-steps",
            "51200", "--variants", "vt=vtnet:pretrain_samples=4096", "b=baseline"]
    val_sweep.main(argv)
    assert calls == [("pretrain", "vt-pretrain-s100", "vt-pretrain-s100"),
                     ("train", "vt-s100", "vt-pretrain-s100"), ("train", "b-s100", None)]
    saved = json.loads((tmp_path / "v.json").read_text())
    assert saved["vt"]["100"]["success"] == 0.512 and saved["b"]["100"]["env_steps"] == 51200
    calls.clear()
    val_sweep.main(argv)                          # both finished: read, nothing trained
    assert calls == []
    check = ["--name", "v", "--out", str(tmp_path), "--check"]   # the summary from the JSON
    assert val_sweep.main(check) == 0
    (tmp_path / "v.md").write_text("edited\n")
    assert val_sweep.main(check) == 1 and calls == []


def test_committed_val_sweep_summaries_agree_with_their_records():
    """`val_sweep.py --name NAME --out DIR --check` on every committed sweep summary:
    NAME.md (mean ± sample std over seeds) is what NAME.json gives."""
    val_sweep = experiment_script("val_sweep")
    summaries = sorted(md for md in (EXPERIMENTS / "results").glob("**/val_choices/*.md")
                       if md.name != "choices.md")
    assert len(summaries) >= 9, summaries
    for md in summaries:
        assert val_sweep.main(["--name", md.stem, "--out", str(md.parent), "--check"]) == 0, md


# ---- issue 55 (bad input, round four): the sweep scripts and the TPN parity check ------


def _fake_evaluations(monkeypatch, calls: list):
    """api.evaluate_run recorded and faked (no evaluation runs): it writes a results
    JSON at `out`, as the real one does."""
    from orgnav_jax import api

    def fake(run_dir, split="test", **kw):
        calls.append((str(run_dir), split, {k: v for k, v in kw.items() if k != "out"}))
        result = {"overall": {"success": 0.5, "spl": 0.25}, "per_room_type": {},
                  "policy": Path(run_dir).name, "split": split}
        Path(kw["out"]).write_text(json.dumps(result))
        return result
    monkeypatch.setattr(api, "evaluate_run", fake)


def test_tpn_lr_sweep_checks_its_run_outputs_and_what_it_resumes(tmp_path, monkeypatch,
                                                                 cli_error):
    """tpn_lr_sweep.py overwrote a user's --out, read whatever results file sat at its
    per-lr path as the sweep's, and on a missing run ended in a traceback naming another
    problem: each is one line, exit 2, before any evaluation; a resume keeps only what
    the record at --out holds for the same run, split and scope."""
    from orgnav_jax.tpn.config import get_tpn_config
    from orgnav_jax.training.config import get_config
    sweep = experiment_script("tpn_lr_sweep")
    calls = []
    _fake_evaluations(monkeypatch, calls)
    tpn = tmp_path / "base" / "tpn"
    tpn.mkdir(parents=True)
    (tpn / "config.json").write_text(get_tpn_config(base_dir=str(tmp_path / "base")).to_json())
    (tmp_path / "base" / "config.json").write_text(get_config("baseline").to_json())
    out = tmp_path / "sweep.json"
    mine = tmp_path / "mine.json"
    mine.write_text("my notes\n")
    (tmp_path / "mine.lr0.001.json").write_text("{}")
    cases = [
        ([tmp_path / "nope", "--out", out], f"{tmp_path / 'nope'}/config.json not found: "
                                            f"{tmp_path / 'nope'} is not a TPN (stage 2) run"),
        ([tmp_path / "base", "--out", out], "not a TPN (stage 2) run, but a training one"),
        ([tpn, "--out", mine], f"--out {mine} exists and is not a TPN learning-rate sweep"),
        ([tpn, "--out", tmp_path / "mine.new", "--lrs", "1e-3"],
         "the results file of lr 0.001 " + str(tmp_path / "mine.lr0.001.json") +
         " exists and is not an evaluation results JSON"),
        ([tpn, "--out", out, "--lrs", "-1"], "TPN config field 'tpn_lr': -1.0"),
        ([tpn, "--out", out, "--lrs", "1e-3", "0.001"], "--lrs: 0.001 given twice"),
        ([tpn, "--out", out, "--scope", "every"], "TPN config field 'scope': 'every'"),
        ([tpn, "--out", ""], "--out is empty"),
    ]
    for argv, message in cases:
        assert message in cli_error(sweep.main, argv), argv
    assert calls == [] and not out.exists() and mine.read_text() == "my notes\n"
    # a first pass, interrupted after lr 0; another policy's results at the path of 1e-3
    record = {"tpn_dir": str(tpn), "split": "val", "scope": "all",
              "results": {"0": {"success": 0.7, "spl": 0.3}}}
    out.write_text(json.dumps(record))
    other = {"overall": {"success": 0.99, "spl": 0.9}, "per_room_type": {}, "split": "test"}
    (tmp_path / "sweep.lr0.001.json").write_text(json.dumps(other))
    assert sweep.main([str(tpn), "--out", str(out), "--lrs", "0", "1e-3"]) == 0
    assert calls == [(str(tpn), "val", {"tpn_lr": 1e-3, "scope": "all", "progress": False})]
    done = json.loads(out.read_text())
    assert done["results"] == {"0": {"success": 0.7, "spl": 0.3},
                               "0.001": {"success": 0.5, "spl": 0.25}}
    # the record of another split (or run, or scope) is not this sweep's
    for change in ({"split": "test"}, {"tpn_dir": str(tmp_path)}, {"scope": "actor"}):
        out.write_text(json.dumps({**record, **change}))
        line = cli_error(sweep.main, [tpn, "--out", out, "--lrs", "0"])
        assert f"--out {out}: the record of another sweep" in line, change
    out.write_text(json.dumps({**record, "results": {"0": {"success": "high"}}}))
    assert "results['0']: field 'success': expected a finite number" in cli_error(
        sweep.main, [tpn, "--out", out, "--lrs", "0"])
    assert len(calls) == 1


def test_savn_act_sweep_refuses_a_users_file_before_any_evaluation(tmp_path, monkeypatch,
                                                                   cli_error):
    """savn_act_sweep.py overwrote a user's --out after two full val evaluations: every
    run, --out and each results file are checked first (one line, exit 2, nothing
    evaluated or written); its own record is replaced."""
    from orgnav_jax.training.config import get_config
    sweep = experiment_script("savn_act_sweep")
    calls = []
    _fake_evaluations(monkeypatch, calls)
    runs = []
    for name, preset, seed in (("dsavn-s100", "dsavn", 100), ("savn-s101", "savn", 101),
                               ("base-s102", "baseline", 102), ("dsavn2-s100", "dsavn", 100)):
        run = tmp_path / name
        run.mkdir()
        (run / "config.json").write_text(get_config(preset, seed=seed,
                                                    run_dir=str(run)).to_json())
        runs.append(run)
    out = tmp_path / "act.json"
    mine = tmp_path / "mine.json"
    mine.write_text('{"my": "table"}')
    (tmp_path / "act.savn-s101.sample.json").write_text("my results\n")
    cases = [
        ([runs[0], "--out", mine], f"--out {mine} exists and is not a sweep JSON"),
        ([runs[0], runs[2], "--out", out], f"{runs[2]}: a baseline run without SAVN"),
        ([runs[0], runs[3], "--out", out], "two runs of seed 100"),
        ([runs[0], tmp_path / "none", "--out", out], "is not a training run directory"),
        ([runs[0], runs[1], "--out", out], "the results file of savn-s101 (sample) "
                                           f"{tmp_path / 'act.savn-s101.sample.json'} exists "
                                           "and is not an evaluation results JSON"),
    ]
    for argv, message in cases:
        assert message in cli_error(sweep.main, argv), argv
    assert calls == [] and not out.exists()
    assert mine.read_text() == '{"my": "table"}'
    assert sweep.main([str(runs[0]), "--out", str(out)]) == 0
    assert [c[2]["savn_act"] for c in calls] == ["greedy", "sample"]
    assert sweep.is_sweep_json(out) and set(json.loads(out.read_text())) == {"greedy", "sample"}
    assert sweep.main([str(runs[0]), "--out", str(out)]) == 0       # its own: replaced


def test_parity_tpn_without_mirror_or_torch_is_one_line_exit_2(tmp_path, cli_error):
    """parity_tpn.py exited 1 on a missing mirror and ended in a traceback on a missing
    --torch-python: one line, exit 2, before anything runs."""
    parity = experiment_script("parity_tpn")
    line = cli_error(parity.main, ["--mirror", tmp_path / "none"])
    assert f"--mirror {tmp_path / 'none'}: no git mirror of the release there" in line
    import subprocess
    mirror = tmp_path / "mirror"
    subprocess.run(["git", "init", "-q", str(mirror)], check=True)
    subprocess.run(["git", "-C", str(mirror), "-c", "user.name=t", "-c", "user.email=t@t",
                    "commit", "-q", "--allow-empty", "-m", "x"], check=True)
    line = cli_error(parity.main, ["--mirror", mirror, "--torch-python", tmp_path / "py"])
    assert f"--torch-python {tmp_path / 'py'}: no such executable" in line
    if importlib.util.find_spec("torch") is None:        # (with torch the check would run)
        line = cli_error(parity.main, ["--mirror", mirror, "--torch-python", sys.executable])
        assert f"--torch-python {sys.executable}: cannot import torch" in line


def test_calibration_table_agrees_with_its_runs():
    """experiments/results/calibration/calibration.md is what the calibration runs'
    committed files give (`calibration.py --check`): val results recomputed from their
    per-episode outcomes, the learning-curve check from metrics.jsonl."""
    calibration = experiment_script("calibration")
    assert calibration.main(["--check"]) == 0
    assert "(chosen)" in (calibration.OUT / "calibration.md").read_text()
    for at in sorted(calibration.OUT.glob("at_*")):         # the calibrations at a budget
        if (at / "calibration.md").exists():
            assert calibration.main(["--budget", at.name[3:], "--check"]) == 0, at
    page = (calibration.OUT / "at_22000000" / "calibration.md").read_text()
    assert "| g5d6v (chosen) |" in page          # the setting calibrated_22m freezes


def test_calibration_settings_name_their_episodes_and_shared_runs():
    """A setting ending in v evaluates on episodes that may start in view: its WE run is
    its global part's with the v kept, its Random the in-view one."""
    from orgnav_jax.tables import calibration as cal
    assert [cal.global_part(s) for s in ("g3d1", "g5d2v", "g5v", "g1")] == \
        ["g3", "g5v", "g5v", "g1"]
    assert cal.random_name("g5d6v") == "random-in-view" and cal.random_name("g3d1") == "random"
    assert cal.episode_distance("g3d1") is None
    assert {lo for lo, _ in dict(cal.episode_distance("g5d6v")).values()} == {0}
    assert all(cal.global_part(s) in cal.SETTINGS for s in cal.SETTINGS)


# round five (issue 67): tables fed the wrong files --------------------------------------

def test_tables_fed_the_wrong_files_are_one_line_and_write_nothing(claims, table_dir,
                                                                   tmp_path_factory,
                                                                   cli_error):
    """claims.py reported a val evaluation as test; judged the calibrated predictions on
    runs made on `small` under a spec naming `calibrated`, and dropped them for a spec
    naming no preset over calibrated runs; run_table.py, resumed across the default
    preset's change, put runs of two presets into one row. Each is one line naming the
    file before anything is written or trained."""
    from orgnav_jax.training.config import get_config
    run_table = experiment_script("run_table")
    results = table_dir / "runs" / "il-s1" / "test_results.json"
    text = results.read_text()
    results.write_text(json.dumps({**json.loads(text), "split": "val"}))
    before = _snapshot(table_dir)
    for argv in ([table_dir], [table_dir, "--check"], [table_dir, "--compact"],
                 [table_dir, "--per-category", "il", "baseline"]):
        assert cli_error(claims.main, argv).endswith(
            f"{results}: field 'split': expected 'test' (the split the table reports), "
            "got 'val'")
    results.write_text(json.dumps({**json.loads(text), "scenes": "small"}))
    assert cli_error(claims.main, [table_dir]).endswith(
        f"{results}: field 'scenes': expected 'calibrated' (the table's scenes: its spec's "
        "config, or the default scene preset), got 'small'")
    results.write_text(text)
    # a run's config on `small` under a spec naming `calibrated` (or none: the default)
    config = table_dir / "runs" / "baseline-s0" / "config.json"
    config.write_text(get_config("baseline", scene_preset="small",
                                 run_dir=str(config.parent)).to_json())
    spec = json.loads((table_dir / "spec.json").read_text())
    want = (f"{config}: the run was trained on 'small', but the table's scenes are "
            "'calibrated' (its spec's config, or the default scene preset where it names "
            "none): a table's runs are on one set of scenes; name theirs in the spec's "
            "config, or use another --out")
    for named in ({}, {"scene_preset": "calibrated"}):
        (table_dir / "spec.json").write_text(json.dumps(dict(spec, config=named)))
        before = _snapshot(table_dir)
        assert cli_error(claims.main, [table_dir]).endswith(want)
        # run_table.py resumed with the spec, or without one (rows of another invocation)
        work = tmp_path_factory.mktemp("spec")
        (work / "s.json").write_text(json.dumps(dict(spec, config=named,
                                                     out=str(table_dir))))
        assert cli_error(run_table.main, ["--spec", work / "s.json"]).endswith(want)
        assert cli_error(run_table.main, ["--out", table_dir, "--rows", "il", "--seeds",
                                          "1"]).endswith(want)
        assert _snapshot(table_dir) == before
    # the runs named right: the predictions of a spec naming no preset are the default's
    config.write_text(get_config("baseline", run_dir=str(config.parent)).to_json())
    names = [c[0] for c in claims_lib.claims("1e-3", dict(spec, config={}))]
    assert "D-SP > WE" in names and "full model > Baseline (paper +12.9)" in names
    assert "D-SP > WE" not in [c[0] for c in claims_lib.claims(
        "1e-3", dict(spec, config={"scene_preset": "small"}))]
    assert claims.main([str(table_dir)]) == 0


@pytest.fixture
def calibration_copy(tmp_path, monkeypatch):
    """experiments/calibration.py over a copy of the calibration runs (OUT patched)."""
    calibration = experiment_script("calibration")
    out = Path(shutil.copytree(calibration.OUT, tmp_path / "calibration"))
    monkeypatch.setattr(calibration, "OUT", out)
    return calibration, out


def test_calibration_check_reads_every_file_through_its_reader(calibration_copy, cli_error):
    """`calibration.py --check` passed a table whose SPL was edited (in the results and
    the page) away from what the per-episode outcomes give, ended in a traceback on a
    val_results.json without per-episode outcomes, and named no file for a cut
    metrics.jsonl line (issue 67; the tables library's readers, tables/runs.py)."""
    calibration, out = calibration_copy
    results = out / "runs" / "baseline-g3d1" / "val_results.json"
    text = results.read_text()
    doc = json.loads(text)
    results.write_text(json.dumps({**doc, "overall": {**doc["overall"], "spl": 0.5}}))
    assert cli_error(calibration.main, ["--check"]).endswith(
        f"{results}: the stored summary differs from its per-episode outcomes in ['spl']")
    results.write_text(json.dumps({k: v for k, v in doc.items() if k != "per_episode"}))
    assert cli_error(calibration.main, ["--check"]).endswith(
        f"{results}: no per-episode outcomes (the release SPL needs them)")
    results.write_text(text)
    metrics = out / "runs" / "baseline-g3d1" / "metrics.jsonl"
    n = len(metrics.read_text().splitlines()) + 1
    with metrics.open("a") as f:
        f.write('{"kind": "val", "env_st')
    assert cli_error(calibration.main, ["--check"]).endswith(
        f"{metrics} line {n}: not valid JSON (expected one JSON object a line)")


def test_calibration_at_another_budget_has_its_own_folder_and_page(calibration_copy, capsys):
    """`calibration.py --budget N`: runs and page in OUT/at_N, the title names N, no
    setting is marked chosen there, Random is the one val evaluation in OUT/runs; a bad
    budget is a one-line error (exit 2) that writes nothing."""
    calibration, out = calibration_copy
    at = out / "at_20000000"
    for run in ("we-g4", "baseline-g4d1"):
        shutil.copytree(out / "runs" / run, at / "runs" / run)
    assert calibration.budget_dir(20_000_000) == at and calibration.budget_dir(5_000_000) == out
    assert calibration.main(["--budget", "20000000", "table"]) == 0
    page = (at / "calibration.md").read_text()
    assert page.startswith("# Perception calibration (val split, seed 100, 20 M env steps)")
    assert "| g4d1 |" in page and "(chosen)" not in page and "| g3d1" not in page
    assert "| 3.6 / 0.013 |" in page                   # Random, from OUT/runs/random
    assert calibration.main(["--budget", "20000000", "--check"]) == 0
    assert calibration.main(["--check"]) == 0          # the 5 M page as it was
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(SystemExit) as exit_:
        calibration.main(["--budget", "-5", "table"])
    assert exit_.value.code == 2 and capsys.readouterr().err.splitlines()[-1].endswith(
        "argument --budget: '-5': expected a whole number of env steps >= 1, e.g. 20000000")
    assert sorted(p.name for p in out.iterdir()) == before
