"""Scale-out (issue 16): data parallel over a 2-device mesh, resume across device counts,
seeds in one program, several processes (bf16: test_mixed_precision.py). The multi-device
checks run in subprocesses (tests/scale_worker.py) with
XLA_FLAGS=--xla_force_host_platform_device_count=2, which must be set before jax is
imported."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import orgnav_jax


WORKER = Path(__file__).with_name("scale_worker.py")
PACKAGE_ROOT = str(Path(orgnav_jax.__file__).resolve().parent.parent)


def subprocess_env(devices: int = 2) -> dict:
    """The environment of a child: this checkout's package first, `devices` CPU devices."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([PACKAGE_ROOT] + [p for p in env.get(
        "PYTHONPATH", "").split(os.pathsep) if p])
    flags = [f for f in env.get("XLA_FLAGS", "").split()
             if not f.startswith("--xla_force_host_platform_device_count")]
    env["XLA_FLAGS"] = " ".join(flags + [f"--xla_force_host_platform_device_count={devices}"])
    env["JAX_PLATFORMS"] = "cpu"
    return env


def leaves(path) -> list[np.ndarray]:
    z = np.load(path)
    return [z[f"arr_{i}"] for i in range(len(z.files))]


def assert_close(a_path, b_path, rtol=1e-5, atol=1e-6):
    """Float leaves within tolerance (reduction order differs across devices), integer
    and bool leaves (env states, counters, keys) equal."""
    a, b = leaves(a_path), leaves(b_path)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x.shape == y.shape and x.dtype == y.dtype
        if x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=rtol, atol=atol)
        else:
            np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def worker_out(tmp_path_factory, tiny_dir):
    """Every worker task in one 2-device subprocess -> OUT, with OUT/TASK/result.json."""
    out = tmp_path_factory.mktemp("worker")
    proc = subprocess.run([sys.executable, str(WORKER), "all", str(out), tiny_dir],
                          env=subprocess_env(), capture_output=True, text=True, timeout=1500)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return out


def task_result(worker_out, task: str):
    return worker_out / task, json.loads((worker_out / task / "result.json").read_text())


@pytest.fixture(scope="module")
def chunk_result(worker_out):
    return task_result(worker_out, "chunk")


@pytest.fixture(scope="module")
def runs_result(worker_out):
    return task_result(worker_out, "runs")


def test_a_chunk_on_two_devices_equals_one_device(chunk_result):
    """3 chunks (6 updates, IL and dropout on) of 16 envs sharded 8 + 8 over 2 devices
    give the parameters, optimizer and env states of the same global batch on one."""
    out, r = chunk_result
    assert r["devices"] == 2 and r["fresh_devices"] == 2 and "data" in r["fresh_spec"]
    assert r["params_replicated"]
    for one, two in r["losses"]:
        assert one == pytest.approx(two, rel=1e-5, abs=1e-6)
    assert_close(out / "one.npz", out / "two.npz")


def test_the_sharded_chunk_is_data_parallel(chunk_result):
    """The gradient mean is an all-reduce; nothing is gathered onto every device (the
    replay flattens the steps env-major, so the env axis stays sharded); one compile."""
    _, r = chunk_result
    assert r["all_reduce"] >= 1 and r["all_gather"] == 0 and r["compiles"] == 1


def test_kill_and_resume_on_two_devices_equals_an_uninterrupted_run(runs_result):
    out, r = runs_result
    assert r["killed2_chunks"] == 2 and r["resumed2_chunks"] == 4
    for a, b in zip(leaves(out / "full2.npz"), leaves(out / "resumed2.npz")):
        np.testing.assert_array_equal(a, b)
    log = [json.loads(line) for line in (out / "killed2" / "metrics.jsonl").open()]
    assert [x["env_steps"] for x in log if x["kind"] == "train"] == [256, 512, 768, 1024]


def test_a_one_device_run_resumes_on_two_devices(runs_result):
    """Checkpoints hold global arrays: a run saved on 1 device continues on 2 (restored,
    then put on the mesh) and ends where a 1-device run ends, within float tolerance."""
    out, r = runs_result
    assert r["moved_chunks"] == 4 and r["moved_fresh_devices"] == 2
    assert_close(out / "full1.npz", out / "one_then_two.npz")
    assert_close(out / "full1.npz", out / "full2.npz")
    assert json.loads((out / "one_then_two" / "config.json").read_text())["devices"] == 2


def test_a_two_device_run_loads_in_a_one_device_process(runs_result):
    """Evaluation and stage 2 load a run's parameters in any process: a checkpoint saved
    from a 2-device mesh restores onto this process's one device (also from shapes
    alone, the latest-checkpoint path of load_run_model)."""
    from orgnav_jax.training.runs import load_run_model
    out, _ = runs_result
    got = latest_params_and_saved(out / "full2", out / "full2.npz")
    for a, b in got:
        np.testing.assert_array_equal(a, b)
    _, best, _ = load_run_model(out / "full2", best=True)
    assert len(jax.tree_util.tree_leaves(best)) == len(got)


def latest_params_and_saved(run_dir, npz) -> list[tuple[np.ndarray, np.ndarray]]:
    """Pairs (leaf of the run's latest checkpointed parameters, read in this 1-device
    process; the same leaf of a runner saved by save_leaves: RunnerState leaves start
    with the parameters)."""
    from orgnav_jax.training.runs import load_run_model
    _, latest, _ = load_run_model(run_dir, best=False)
    got = [np.asarray(x) for x in jax.tree_util.tree_leaves(latest)]
    return list(zip(got, leaves(npz)[:len(got)]))


def _cli(args, tmp_path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "orgnav_jax.train", *map(str, args)],
                          env=subprocess_env(), capture_output=True, text=True,
                          timeout=300, cwd=tmp_path)


def test_devices_errors_are_one_line(tmp_path, tiny_dir):
    base = ["--preset", "tiny", "--scenes-dir", tiny_dir, "--run-dir", tmp_path / "r"]
    for extra, message in ((["--devices", "2", "--num-envs", "15"],
                            "error: num_envs 15 does not divide by the 2 devices"),
                           (["--devices", "3"], "error: --devices 3: this process sees 2 cpu")):
        proc = _cli(base + extra, tmp_path)
        assert proc.returncode == 2, proc.stderr[-2000:]
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith(message), last
        assert "Traceback" not in proc.stderr
    assert not (tmp_path / "r").exists()


# ------------------------------------------------------------------ seeds in one program

def records(run_dir, kind: str) -> list[dict]:
    return [r for r in map(json.loads, (Path(run_dir) / "metrics.jsonl").open())
            if r["kind"] == kind]


def assert_records_close(a: list[dict], b: list[dict], skip=("steps_per_s",)):
    assert len(a) == len(b) and a
    for x, y in zip(a, b):
        assert set(x) == set(y)
        for k in x:
            if k in skip:
                continue
            if isinstance(x[k], (int, float)) and not isinstance(x[k], bool):
                assert x[k] == pytest.approx(y[k], rel=1e-5, abs=1e-6), (k, x, y)
            else:                   # names, flags: exact (pytest 9 refuses approx on str)
                assert x[k] == y[k], (k, x, y)


def test_seeds_in_one_program_equal_separate_runs(tmp_path, tiny_dir, capsys):
    """`--seeds 0 1` (one vmapped program, RUN_DIR-s0 and RUN_DIR-s1) gives each seed the
    parameters of a separate run within float tolerance, the same val records, its own
    config, log and checkpoints."""
    from orgnav_jax import train as train_cli
    from orgnav_jax.training import loop
    from orgnav_jax.training.runs import load_run_model
    small = ["--preset", "tiny", "--scenes-dir", tiny_dir, "--num-envs", 16, "--rollout-len",
             8, "--updates-per-chunk", 2, "--total-env-steps", 1024, "--eval-every-chunks", 2,
             "--eval-episodes-per-room-type", 4, "--checkpoint-every-chunks", 1, "--il",
             "deadlock", "--no-test", "--quiet"]
    out = train_cli.main([str(a) for a in small + ["--run-dir", tmp_path / "pop",
                                                    "--seeds", 0, 1]])
    err = capsys.readouterr().err
    assert "steps/s (2 runs together) over chunks 2-3 (compile excluded): the remaining 1 " \
        "of 4 chunks take about" in err
    assert [r["run_dir"] for r in out["runs"]] == [str(tmp_path / "pop-s0"),
                                                   str(tmp_path / "pop-s1")]
    assert not (tmp_path / "pop").exists()
    for seed in (0, 1):
        cfg = loop.load_config(tmp_path / f"pop-s{seed}")
        assert cfg.seed == seed
        alone = dataclasses.replace(cfg, run_dir=str(tmp_path / f"alone-s{seed}"))
        loop.train(alone, progress=False)
        assert_records_close(records(tmp_path / f"pop-s{seed}", "train"),
                             records(tmp_path / f"alone-s{seed}", "train"))
        assert [dict(r) for r in records(tmp_path / f"pop-s{seed}", "val")] == \
            records(tmp_path / f"alone-s{seed}", "val")
        _, a, _ = load_run_model(tmp_path / f"pop-s{seed}", best=False)
        _, b, _ = load_run_model(tmp_path / f"alone-s{seed}", best=False)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-5, atol=1e-6)
    # the two seeds really differ
    s0 = records(tmp_path / "pop-s0", "train")[0]
    s1 = records(tmp_path / "pop-s1", "train")[0]
    assert s0["loss"] != s1["loss"]


@pytest.fixture(scope="module")
def seeds_result(worker_out):
    return task_result(worker_out, "seeds")


def test_seeds_on_two_devices_resume_and_equal_separate_runs(seeds_result):
    """A population on 2 devices (seed axis vmapped, env axis sharded): killed after 2
    chunks and resumed it equals the uninterrupted population; each seed equals its
    separate 1-device run within float tolerance."""
    out, r = seeds_result
    assert r["killed_chunks"] == [2, 2] and r["resumed_chunks"] == [4, 4]
    assert r["fresh_devices"] == 2
    for seed in (0, 1):
        for a, b in zip(leaves(out / f"pop-s{seed}.npz"),
                        leaves(out / f"resumed-s{seed}.npz")):
            np.testing.assert_array_equal(a, b)
        assert_close(out / f"one-s{seed}.npz", out / f"pop-s{seed}.npz")
        assert [x["env_steps"] for x in records(out / f"killed-s{seed}", "train")] == \
            [256, 512, 768, 1024]


def test_seeds_errors(tmp_path, tiny_dir, cli_error):
    from orgnav_jax import train as train_cli
    base = ["--preset", "tiny", "--scenes-dir", tiny_dir, "--run-dir", tmp_path / "r"]
    assert cli_error(train_cli.main, base + ["--seeds", 0, 0]) == \
        "error: --seeds 0 0: expected distinct seeds"
    assert cli_error(train_cli.main, base + ["--seeds", 0, 1, "--seed", 3]) == \
        "error: --seed and --seeds: give one"
    assert not (tmp_path / "r-s0").exists()


def test_run_table_trains_the_seeds_of_a_row_in_one_program(tmp_path, tiny_dir, monkeypatch):
    """experiments/run_table.py --population: the row's seeds train through
    api.train_seeds (one program), then each is tested and tabled as before."""
    import importlib.util

    from orgnav_jax import api
    path = Path(__file__).parents[1] / "experiments" / "run_table.py"
    spec = importlib.util.spec_from_file_location("run_table", path)
    run_table = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(run_table)
    calls = []
    real = api.train_seeds
    monkeypatch.setattr(api, "train_seeds",
                        lambda cfg, seeds, **kw: calls.append(list(seeds)) or
                        real(cfg, seeds, **kw))
    # run_one then resumes each finished run (a no-op) before testing it
    real_train = api.train
    monkeypatch.setattr(api, "train", lambda cfg, resume=False, **kw: real_train(
        cfg, resume=resume, **kw) if resume else pytest.fail("trained one by one"))
    out = tmp_path / "table"
    args = ["--rows", "baseline", "--seeds", "0", "1", "--population", "--out", str(out),
            "--scenes-dir", tiny_dir, "--num-envs", "16", "--rollout-len", "8",
            "--updates-per-chunk", "2", "--total-env-steps", "512", "--eval-every-chunks",
            "2", "--eval-episodes-per-room-type", "4"]
    run_table.main(args)
    assert calls == [[0, 1]]
    results = json.loads((out / "results.json").read_text())
    assert sorted(results["baseline"]) == ["0", "1"]
    for seed in (0, 1):
        assert (out / "runs" / f"baseline-s{seed}" / "test_results.json").exists()
        assert loop_config(out / "runs" / f"baseline-s{seed}").seed == seed
        assert [r["env_steps"] for r in records(out / "runs" / f"baseline-s{seed}",
                                                "train")] == [256, 512]
    # killed after training, before its tests: the rerun trains nothing and says so
    for seed in (0, 1):
        (out / "runs" / f"baseline-s{seed}" / "test_results.json").unlink()
    run_table.main(args)
    assert calls == [[0, 1], [0, 1]]
    for seed in (0, 1):
        did = [r["did"] for r in json.loads(
            (out / "runs" / f"baseline-s{seed}" / "provenance.json").read_text())]
        assert did.count("trained in one program with seeds 0 1") == 1, did
        assert (out / "runs" / f"baseline-s{seed}" / "test_results.json").exists()


def loop_config(run_dir):
    from orgnav_jax.training.config import load_config
    return load_config(run_dir)


# ------------------------------------------------------------------ several processes

def free_port() -> int:
    import socket
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def two_processes(args, tmp_path, timeout: int = 600) -> list[subprocess.CompletedProcess]:
    """`python -m orgnav_jax.train ARGS` as processes 0 and 1 of a jax.distributed job on
    this machine (one CPU device each, gloo collectives) -> both results."""
    port = free_port()
    procs = [subprocess.Popen(
        [sys.executable, "-m", "orgnav_jax.train", *map(str, args), "--coordinator",
         f"localhost:{port}", "--num-processes", "2", "--process-id", str(i)],
        env=subprocess_env(devices=1), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, cwd=tmp_path) for i in (0, 1)]
    results = []
    try:
        for p in procs:
            out, err = p.communicate(timeout=timeout)
            results.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for r in results:
        assert r.returncode == 0, r.stderr[-4000:]
    return results


def printed(proc) -> list[str]:
    """stdout lines of a process other than gloo's connection notice."""
    return [line for line in proc.stdout.splitlines() if not line.startswith("[Gloo]")]


@pytest.mark.slow      # ~30 s alone: two process starts, each compiling the chunk
def test_two_processes_resume_a_run_and_write_one_set_of_logs(tmp_path, runs_result):
    """2 processes x 1 CPU device (jax.distributed, gloo) resume, as one 2-device mesh, a
    copy of a finished 2-chunk run that one process saved on 2 devices, extending its
    budget to 4 chunks: both restore its checkpoint; process 0 alone rewrites config.json,
    appends to metrics.jsonl and TensorBoard and prints; the new checkpoints are written
    together. The records equal a 1-process 2-device run's, and the last checkpoint (read
    back in this 1-device process) holds that run's parameters (float tolerance). (One
    job, not a fresh one and its resume: each 2-process job costs ~45 CPU-seconds of the
    suite; docs/history/test-suite-time.md.)"""
    out, r = runs_result                      # the worker's runs: the same computation
    assert r["half2_chunks"] == 2
    run = shutil.copytree(out / "half2", tmp_path / "run")
    procs = two_processes(["--resume", "--run-dir", run, "--total-env-steps", 1024,
                           "--no-test", "--quiet"], tmp_path)
    assert '"chunks": 4' in procs[0].stdout and printed(procs[1]) == []
    assert sorted(p.name for p in run.iterdir() if not p.name.startswith("tb")) == \
        ["best", "checkpoints", "config.json", "metrics.jsonl"]
    assert [r["env_steps"] for r in records(run, "train")] == [256, 512, 768, 1024]
    assert_records_close(records(run, "train"), records(out / "full2", "train"))
    assert_records_close(records(run, "val"), records(out / "full2", "val"))
    assert json.loads((run / "config.json").read_text())["total_env_steps"] == 1024
    for a, b in latest_params_and_saved(run, out / "full2.npz"):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_process_options_go_together(tmp_path, tiny_dir, cli_error):
    from orgnav_jax import train as train_cli
    base = ["--preset", "tiny", "--scenes-dir", tiny_dir, "--run-dir", tmp_path / "r"]
    assert "--coordinator, --num-processes and --process-id go together" in cli_error(
        train_cli.main, base + ["--coordinator", "localhost:1234"])
    assert "expected HOST:PORT" in cli_error(
        train_cli.main, base + ["--coordinator", "localhost", "--num-processes", 2,
                                "--process-id", 0])
    assert "0 <= process id < number of processes" in cli_error(
        train_cli.main, base + ["--coordinator", "localhost:1", "--num-processes", 2,
                                "--process-id", 2])


# ------------------------------------------------------------------ the paper's budget

def test_budget_paper_is_6m_episodes_and_2m_tpn_episodes(cli_error, tmp_path):
    """Stage 1 counts env steps: 6 M episodes x 16 steps (the measured mean training
    episode length) = 96 M; the TPN counts episodes: 2 M."""
    from orgnav_jax import train as train_cli
    from orgnav_jax.training.config import BUDGETS
    paper = BUDGETS["paper"]
    assert (paper.episodes, paper.steps_per_episode, paper.tpn_episodes) == \
        (6_000_000, 16, 2_000_000)
    cfg = train_cli.nav_config(train_cli.parser().parse_args(["--budget", "paper"]))
    assert cfg.total_env_steps == 96_000_000
    assert cfg.budget_notice() is None                 # 96 M is whole chunks: run exactly
    assert "6,000,000 episodes x 16 env steps per episode" in paper.describe()
    assert cli_error(train_cli.main, ["--budget", "paper", "--total-env-steps", "5"]) == \
        "error: --budget and --total-env-steps set the same budget: give one"
    assert cli_error(train_cli.main, ["--stage", "tpn", "--budget", "paper",
                                      "--total-episodes", "5"]) == \
        "error: --budget and --total-episodes set the same budget: give one"


def test_wall_time_estimate_from_the_timed_chunks():
    from orgnav_jax.training.driver import Stage, wall_time_estimate
    stage = Stage(name="train org", unit="step", step_name="env_steps",
                  rate_key="steps_per_s", per_chunk=25_600, total=96_000_000,
                  chunk=None, summarize=None, validate=None, score_keys=("success",),
                  best_keys=("success",))
    text = wall_time_estimate(stage, chunk=3, seconds=[2.0, 2.0], members=1)
    assert text.startswith("train org: 12,800 steps/s over chunks 2-3 (compile excluded): "
                           "the remaining 3747 of 3750 chunks take about 2.1 h")
    assert "(a whole run: 2.1 h;" in text
    three = wall_time_estimate(stage, chunk=3, seconds=[2.0, 2.0], members=3)
    assert "38,400 steps/s (3 runs together)" in three
    capped = wall_time_estimate(stage, chunk=3, seconds=[2.0, 2.0], members=3, capped=True)
    assert capped.endswith("checkpoints extra; the budget is a cap, the convergence rule may "
                           "stop it sooner)")
    assert not three.endswith("sooner)")


def test_the_estimate_with_evaluations_from_two_evaluation_marks():
    from orgnav_jax.training.driver import Stage, cycle_estimate
    stage = Stage(name="train org", unit="step", step_name="env_steps",
                  rate_key="steps_per_s", per_chunk=25_600, total=22_016_000,
                  chunk=None, summarize=None, validate=None, score_keys=("success",),
                  best_keys=("success",))
    # 8 chunks and an evaluation in 80 s: 10 s a chunk, 5 runs
    text = cycle_estimate(stage, [(8, 100.0), (16, 180.0)], members=5)
    assert text == ("train org: 12,800 steps/s (5 runs together) with evaluations and "
                    "checkpoints, over chunks 9-16: the remaining 844 of 860 chunks take "
                    "about 2.3 h")
    assert cycle_estimate(stage, [(8, 100.0), (16, 180.0)], 5, capped=True).endswith(
        "2.3 h; the budget is a cap, the convergence rule may stop it sooner")


# ------------------------------------------------------------------ config fields

def test_scale_out_config_fields_and_older_configs(tmp_path):
    """devices and dtype are checked like every field; a version-3 config.json (before
    them) reads as one device in float32, and --resume may change devices only."""
    from orgnav_jax.training.config import get_config, load_config
    from orgnav_jax.training.run_dir import config_differences, write_config
    with pytest.raises(ValueError, match=r"config field 'dtype': 'float16', expected one of "
                                         r"\['float32', 'bfloat16'\]"):
        get_config("tiny", dtype="float16")
    with pytest.raises(ValueError, match=r"'devices': -1, expected an integer devices >= 0 "
                                         r"\(0: all local devices\)"):
        get_config("tiny", devices=-1)
    cfg = get_config("tiny", run_dir=str(tmp_path))
    write_config(tmp_path, cfg)
    doc = json.loads((tmp_path / "config.json").read_text())
    assert doc["version"] >= 4 and doc["devices"] == 0 and doc["dtype"] == "float32"
    old = {k: v for k, v in doc.items() if k not in ("devices", "dtype")}
    old["max_steps"] = old.pop("episode_cap")           # its name before version 5
    (tmp_path / "config.json").write_text(json.dumps(dict(old, version=3)))
    assert load_config(tmp_path) == cfg
    assert config_differences(cfg, dataclasses.replace(cfg, devices=2)) == []
    assert config_differences(cfg, dataclasses.replace(cfg, dtype="bfloat16")) == \
        ["dtype: 'float32' -> 'bfloat16'"]
