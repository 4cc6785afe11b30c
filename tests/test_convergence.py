"""The convergence rule (orgnav_jax/tables/convergence.py) on synthetic val curves
(flat, rising, noisy, falling), its reading of metrics.jsonl, the trainer's stop
criterion on a stand-in stage (no network, no compile), and --until-converged's bad
values. None of these is a learning test."""

from __future__ import annotations

import json

import flax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax.tables import convergence as cv
from orgnav_jax.training.config import get_config
from orgnav_jax.training.driver import Stage, run_population

STEP = 204_800


def curve(*success_per_seed, episodes: int = 1000) -> cv.SeedMeanCurve:
    """Seed curves of val success (fractions), evaluated every STEP env steps."""
    runs = [cv.ValCurve(f"seed {i}", STEP * np.arange(1, len(s) + 1), np.asarray(s, float),
                        np.full(len(s), episodes)) for i, s in enumerate(success_per_seed)]
    return cv.seed_mean_curve(runs)


def test_a_flat_curve_has_converged_and_a_rising_one_has_not():
    flat = np.full(40, 0.60)
    v = cv.judge(curve(flat, flat))
    assert v.converged and v.change == pytest.approx(0.0) and v.env_steps == 40 * STEP
    rising = np.linspace(0.10, 0.60, 40)          # +0.5 points an evaluation
    r = cv.judge(curve(rising, rising))
    # quarters of 10 evaluations, 50/39 points apart each: 12.8 points apart
    assert not r.converged and r.change == pytest.approx(100 * 0.5 / 39 * 10)
    assert "beyond 1" in r.why


def test_the_rule_asks_the_quarter_test_to_hold_from_b_to_a_quarter_more():
    flat = np.full(49, 0.60)
    v = cv.converged(curve(flat, flat))           # held since 40 evaluations, not to 50
    assert not v.converged and v.budget is None and "confirmed at 1.25 x that" in v.why
    v = cv.converged(curve(np.full(50, 0.6), np.full(50, 0.6)))
    assert v.converged and v.budget == 40 * STEP and "converged at B = 8,192,000" in v.why
    # a break in the run of evaluations where the quarter test holds starts it again
    s = np.r_[np.full(44, 0.60), np.full(100, 0.66)]    # a 6-point step at 44
    assert cv.judge(curve(s, s), upto=44).converged
    first = cv.converged_at(curve(s, s))
    assert first.budget > 80 * STEP and first.env_steps >= 1.25 * first.budget


def test_the_rule_judges_the_seed_mean_and_its_quarters():
    """Two seeds rising in opposite directions average to flat: converged; the quarters
    are the last n // 4 evaluations against the n // 4 before them."""
    up, down = np.linspace(0.4, 0.6, 40), np.linspace(0.6, 0.4, 40)
    assert cv.judge(curve(up, down)).converged
    s = np.r_[np.full(22, 0.50), np.full(8, 0.52), np.full(10, 0.535)]   # n=40, q=10
    v = cv.judge(curve(s, s))
    assert v.quarter_before == pytest.approx((2 * 50 + 8 * 52) / 10)
    assert v.last_quarter == pytest.approx(53.5)
    assert not v.converged and v.change == pytest.approx(1.9)


def test_a_noisy_plateau_converges_and_a_late_rise_is_seen():
    rng = np.random.default_rng(0)
    steps = 100
    base = np.minimum(np.linspace(0.05, 1.5, steps), 0.58)   # rises, then a plateau at 58
    # from evaluation 37 on
    seeds = [np.clip(base + rng.normal(0, 0.015, steps), 0, 1) for _ in range(2)]
    c = curve(*seeds)
    first = cv.converged_at(c)
    assert first is not None and first.converged
    # the rule needs its last two quarters (nearly) on the plateau
    assert 55 < first.evaluations <= steps and first.env_steps == first.evaluations * STEP
    assert not cv.judge(c, upto=50).converged       # half of it still rising
    late = [np.r_[s[:80], s[80:] + 0.05] for s in seeds]   # +5 points in the last 20
    assert not cv.judge(curve(*late)).converged


def test_a_falling_curve_has_not_converged_and_short_curves_are_not_judged():
    falling = np.linspace(0.6, 0.3, 40)
    assert not cv.judge(curve(falling, falling)).converged
    short = cv.judge(curve(np.full(39, 0.5), np.full(39, 0.5)))
    assert not short.converged and short.change is None and "at least 40" in short.why
    assert cv.converged_at(curve(np.linspace(0.1, 0.9, 30), np.linspace(0.1, 0.9, 30))) is None


def test_the_rule_refuses_one_seed_and_small_evaluations():
    with pytest.raises(ValueError, match="at least 2 seeds"):
        cv.judge(curve(np.full(20, 0.5)))
    with pytest.raises(ValueError, match="val evaluations of 200 episodes: the rule needs "
                                         "at least 1,000"):
        cv.judge(curve(np.full(20, 0.5), np.full(20, 0.5), episodes=200))


def write_metrics(run_dir, success, episodes=1000, extra_last=False, cut=False, step=STEP):
    run_dir.mkdir(parents=True)
    lines = []
    for i, s in enumerate(success, 1):
        lines.append({"kind": "train", "env_steps": i * step, "success": 0.1})
        lines.append({"kind": "val", "env_steps": i * step, "episodes": episodes,
                      "success": s, "spl": 0.2})
    text = "".join(json.dumps(r) + "\n" for r in lines)
    if cut:
        text += '{"kind": "val", "env_st'
    (run_dir / "metrics.jsonl").write_text(text)


def test_check_runs_reads_the_runs_metrics_and_their_shared_steps(tmp_path):
    write_metrics(tmp_path / "a", [0.5] * 51, cut=True)    # one more evaluation, a cut line
    write_metrics(tmp_path / "b", [0.5] * 50)
    v = cv.check_runs([tmp_path / "a", tmp_path / "b"])
    assert v.converged and v.evaluations == 50 and v.env_steps == 50 * STEP
    assert v.budget == 40 * STEP                # held from 40 evaluations, to 1.25 x that
    write_metrics(tmp_path / "c", [])
    with pytest.raises(ValueError, match=r"c/metrics.jsonl: no val evaluation"):
        cv.read_val_curve(tmp_path / "c")
    write_metrics(tmp_path / "d", [1.5] * 20)
    with pytest.raises(ValueError, match="d/metrics.jsonl: a val success outside"):
        cv.read_val_curve(tmp_path / "d")


@flax.struct.dataclass
class Counter:
    params: dict            # {"n": the chunks done} (the field the driver's best reads)


def stand_in_stage(success_of_chunk) -> Stage:
    """A stage with no network: the runner counts chunks; val success is scripted."""
    return Stage(name="train stand-in", unit="step", step_name="env_steps",
                 rate_key="steps_per_s", per_chunk=STEP, total=200 * STEP,
                 chunk=lambda r: (Counter({"n": r.params["n"] + 1}),
                                  {"loss_finite": jnp.array([True] * 2)}),
                 summarize=lambda m: {}, score_keys=("success",), best_keys=("success",),
                 validate=lambda r: {"success": success_of_chunk(int(r.params["n"])),
                                     "episodes": 1000.0})


def test_the_trainer_stops_when_the_rule_holds_and_resumes_to_the_cap(tmp_path):
    cfg = get_config("tiny", eval_every_chunks=1, checkpoint_every_chunks=1000)
    dirs = [tmp_path / "r-s0", tmp_path / "r-s1"]
    for d in dirs:
        d.mkdir()
    plateau = lambda n: min(0.01 * n, 0.5)            # flat from chunk 50
    runners = [Counter({"n": jnp.array(0)}) for _ in dirs]
    out = run_population(stand_in_stage(plateau), runners, [cfg, cfg], dirs, resume=False,
                         progress=False, stop=cv.stop_when_converged())
    stopped_at = out[0]["env_steps"]
    assert out[0]["stopped"].startswith("converged: seed-mean val success 50.0")
    assert 50 * STEP < stopped_at < 200 * STEP
    assert cv.check_runs(dirs).converged and cv.check_runs(dirs).env_steps == stopped_at
    # resumed with the rule, which holds there: no more training, no more evaluations
    again = run_population(stand_in_stage(plateau), runners, [cfg, cfg], dirs, resume=True,
                           progress=False, stop=cv.stop_when_converged())
    assert again[0]["env_steps"] == stopped_at and again[0]["stopped"] == out[0]["stopped"]
    assert again[0]["chunks_run"] == 0 and out[0]["chunks_run"] == stopped_at // STEP
    assert cv.check_runs(dirs).evaluations == stopped_at // STEP
    # a checkpoint at the stop: --resume continues there, to the cap without the rule
    out = run_population(stand_in_stage(plateau), runners, [cfg, cfg], dirs, resume=True,
                         progress=False)
    assert out[0]["env_steps"] == 200 * STEP and out[0]["stopped"] is None
    records = [json.loads(x) for x in (dirs[0] / "metrics.jsonl").read_text().splitlines()]
    assert [r["env_steps"] for r in records if r["kind"] == "val"] == \
        [STEP * i for i in range(1, 201)]


@pytest.mark.parametrize("args, message", [
    (["--until-converged"], "--until-converged goes with stage-1 training of --seeds"),
    (["--until-converged", "--seeds", "100"], "at least 2 seeds trained in one program"),
    (["--until-converged", "--seeds", "100", "101"],
     "--eval-episodes-per-room-type 50 gives val evaluations of 200 episodes"),
    (["--until-converged", "--stage", "pretrain", "--seeds", "1", "2"], "not pre-training"),
])
def test_until_converged_bad_values_are_one_line_errors(args, message, tmp_path, capsys):
    from orgnav_jax import train
    from orgnav_jax.errors import run_cli
    run_dir = tmp_path / "run"
    assert run_cli(train.main, [*args, "--preset", "tiny", "--run-dir", str(run_dir)]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not any(tmp_path.iterdir())      # nothing written


def test_the_campaign_page_judges_each_row_and_check_sees_a_change(tmp_path, capsys):
    from orgnav_jax.tables.convergence_page import report, verdict_lines, rows_of
    from orgnav_jax.tables.pages import regenerate
    from orgnav_jax.training.run_dir import write_config
    out, table = tmp_path / "convergence", tmp_path / "table"
    plateau = [min(0.02 * i, 0.5) for i in range(1, 61)]
    for seed in (100, 101):
        write_metrics(out / "runs" / f"flat-s{seed}", plateau)
        write_metrics(out / "runs" / f"rising-s{seed}", np.linspace(0.1, 0.6, 45).tolist())
        write_config(out / "runs" / f"flat-s{seed}", get_config("tiny"))
        write_config(out / "runs" / f"rising-s{seed}", get_config("tiny"))
    for seed in range(2):
        write_metrics(table / "runs" / f"baseline-s{seed}", np.linspace(0.1, 0.5, 50).tolist(),
                      episodes=200)
    text = report(out, table, tmp_path)
    assert "| flat | baseline, IL none, 64 envs x 16 steps, lr 0.0007 | 100, 101 | 60 | " \
           "12,288,000 | 50.0 | 50.0 | +0.0 | converged | " in text
    assert "| rising |" in text and "| not converged | - |" in text
    assert "| baseline | 2 | " in text            # the table's rows by tenth
    lines = verdict_lines(rows_of(sorted((out / "runs").iterdir())))
    assert lines[0].startswith("flat: converged (seed-mean val success 50.0")
    assert lines[1].startswith("rising: not converged") and "has not said converged yet" in lines[1]
    page = {out / "report.md": text}
    assert regenerate(page, check=False) == 0 and regenerate(page, check=True) == 0
    write_metrics(out / "runs" / "flat-s102", plateau[:-1] + [0.9])
    page = {out / "report.md": report(out, table, tmp_path)}
    assert regenerate(page, check=True) == 1
    assert "report.md: differs" in capsys.readouterr().err


def test_a_converged_table_judges_each_trained_row_and_says_so_in_its_claims(tmp_path,
                                                                             capsys):
    """A spec with "converged": true: convergence.md has the rule on each trained
    navigation row (a TPN row's base once, not random), claims.md names the rows not
    converged and their claims, and --check sees a changed curve."""
    from helpers import experiment_script
    from orgnav_jax.tables import table_files
    claims = experiment_script("claims")
    spec = {"out": str(tmp_path), "seeds": [0, 1], "population": True, "converged": True,
            "config": {"eval_episodes_per_room_type": 250}, "tpn": {},
            "rows": ["random", "baseline", "il", "org", "dsp", "baseline+tpn@1e-4", "we"]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    runs = tmp_path / "runs"
    for seed in (0, 1):
        write_metrics(runs / f"baseline-s{seed}", [0.5] * 50)                  # flat
        write_metrics(runs / f"il-s{seed}", np.linspace(0.1, 0.6, 50).tolist())  # rising
        write_metrics(runs / f"org-s{seed}", [0.5] * 50, episodes=200)
    write_metrics(runs / "dsp-s0", [0.5] * 50)
    write_metrics(runs / "dsp-s1", [0.5] * 50, step=STEP + 1)      # no step in common
    assert claims.main([str(tmp_path)]) == 0
    page = (tmp_path / "convergence.md").read_text().splitlines()
    rows = {line.split(" | ")[0][2:]: line for line in page if line.startswith("| ")}
    assert list(rows) == ["row", "baseline", "il", "org", "dsp", "we"]
    assert rows["baseline"] == ("| baseline | 0, 1 | 50 | 10,240,000 | 50.0 | 50.0 | +0.0 | "
                                "converged (B' = 8,192,000) |")
    assert rows["il"].endswith("| not converged |") and "| 0, 1 | 50 | " in rows["il"]
    assert rows["org"].endswith("| not judged: val evaluations of 200 episodes: the rule "
                                "needs at least 1,000 (--eval-episodes-per-room-type 250) |")
    assert rows["dsp"].endswith("| not judged: the runs share no val evaluation step: "
                                "dsp-s0, dsp-s1 |")
    assert rows["we"] == "| we | | | | | | | no runs yet |"
    text = (tmp_path / "claims.md").read_text()
    assert "**Not converged** by the convergence rule at their last val evaluation " \
           "(convergence.md): il, org, dsp." in text       # we: no runs, not measured
    notes = [x[2:] for x in text.splitlines() if x.startswith("- ")]
    assert notes == ["ORG > Baseline", "ORG > D-SP", "IL > Baseline",
                     "D-SP > WE"]                 # (a prediction of the calibrated preset)
    assert "| Baseline > WE | not measured |" in text
    assert "- Baseline + TPN > Baseline" not in text        # baseline has converged
    assert claims.main(["--check", str(tmp_path)]) == 0
    write_metrics(runs / "baseline-s2", [0.5] * 50)         # not a seed of the spec
    assert table_files.check(tmp_path) == []
    (runs / "il-s1" / "metrics.jsonl").unlink()
    assert claims.main(["--check", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "convergence.md: differs" in err and "claims.md: differs" not in err
    spec["converged"] = False                   # without the rule: no page, no note
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    files = table_files.expected_files(tmp_path)
    assert "convergence.md" not in files and "Not converged" not in files["claims.md"]


def test_the_committed_campaign_page_agrees_with_its_runs():
    """experiments/results/convergence/report.md is what its runs' committed files give
    (`python experiments/convergence.py report --check`)."""
    from pathlib import Path
    from orgnav_jax.tables.convergence_page import report
    root = Path(__file__).resolve().parents[1]
    out = root / "experiments" / "results" / "convergence"
    text = report(out, root / "experiments" / "results" / "table_calibrated", root)
    assert (out / "report.md").read_text() == text


def test_the_campaign_run_starts_resumes_and_records_why_it_stopped(tmp_path, monkeypatch):
    """`convergence.py run ROW`: a fresh row starts with the campaign's setting, a second
    call resumes it with its saved config and the cap; every process leaves a provenance
    record in both runs, also when interrupted (training is a stand-in here)."""
    from helpers import experiment_script
    from orgnav_jax.tables.provenance import read_provenance
    from orgnav_jax.training.run_dir import write_config
    script = experiment_script("convergence")
    calls = []

    def stand_in(cfg, seeds, resume, progress, until_converged):
        calls.append((cfg, resume, until_converged))
        for s in seeds:
            run = tmp_path / "runs" / f"baseline_16envs-s{s}"
            if not resume:
                write_metrics(run, [0.5] * 3)
                write_config(run, cfg)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return [{"stopped": "converged: the rule"}] * len(seeds)

    monkeypatch.setattr(script.api, "train_seeds", stand_in)
    assert script.run_row("baseline_16envs", tmp_path) == "stopped by the rule: converged: the rule"
    cfg, resume, until = calls[0]
    assert (cfg.num_envs, cfg.updates_per_chunk, cfg.scene_preset, cfg.total_env_steps,
            cfg.eval_episodes_per_room_type, resume, until) == (16, 100, "calibrated",
                                                                script.CAP, 250, False, True)
    with pytest.raises(KeyboardInterrupt):
        script.run_row("baseline_16envs", tmp_path)
    assert calls[1][1] is True and calls[1][0].num_envs == 16     # resumed, saved config
    for s in script.SEEDS:
        did = [r["did"] for r in read_provenance(
            tmp_path / "runs" / f"baseline_16envs-s{s}" / "provenance.json")]
        assert did[0].startswith("trained in one program with seeds 100 101 until converged")
        assert did[0].endswith("stopped by the rule: converged: the rule")
        assert did[1].startswith("resumed") and did[1].endswith(
            f"interrupted at about {3 * STEP:,} env steps")
    assert len(calls) == 2 and not (tmp_path / "runs" / "we-s100").exists()  # only ROW's runs


def test_the_tables_budget_is_the_latest_said_converged_rounded_up_to_a_million():
    """table_budget: the largest env step where the rule first said converged among the
    Baseline, WE and ORG + IL, rounded up to whole millions; None while one has not."""
    from orgnav_jax.tables.convergence_page import first_converged, table_budget
    flat = curve(np.full(60, 0.5), np.full(60, 0.5))
    later = curve(np.r_[np.linspace(0.1, 0.5, 30), np.full(70, 0.5)],
                  np.r_[np.linspace(0.1, 0.5, 30), np.full(70, 0.5)])
    said = [cv.converged_at(c).env_steps for c in (flat, later)]
    assert said[0] < said[1]
    budget, text = table_budget(first_converged({"baseline": flat, "we": later,
                                                 "org_il": flat}))
    assert budget == -(-said[1] // 1_000_000) * 1_000_000 and budget > said[1]
    assert text.startswith(f"**{budget:,} env steps**") and f"we {said[1]:,}" in text
    budget, text = table_budget(first_converged(
        {"baseline": flat, "we": curve(np.linspace(0.1, 0.6, 60), np.linspace(0.1, 0.6, 60))}))
    assert budget is None and text.startswith("Not fixed yet: we, org_il not converged")
