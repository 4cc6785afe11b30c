"""Scale-out (issue 16): data parallel over a 2-device mesh, resume across device counts,
seeds in one program, several processes, bf16. The multi-device checks run in
subprocesses (tests/scale_worker.py) with XLA_FLAGS=--xla_force_host_platform_device_count=2,
which must be set before jax is imported."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import orgnav_jax
from orgnav_jax import scenes as scenes_mod

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


def run_worker(task: str, out: Path, scenes_dir: str, *args, timeout: int = 900) -> dict:
    proc = subprocess.run([sys.executable, str(WORKER), task, str(out), scenes_dir,
                           *map(str, args)], env=subprocess_env(), capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads((out / "result.json").read_text())


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
def tiny_dir(tmp_path_factory, tiny_scenes):
    path = tmp_path_factory.mktemp("scenes") / "tiny"
    scenes_mod.save(tiny_scenes, path)
    return str(path)


@pytest.fixture(scope="module")
def chunk_result(tmp_path_factory, tiny_dir):
    out = tmp_path_factory.mktemp("chunk")
    return out, run_worker("chunk", out, tiny_dir)


@pytest.fixture(scope="module")
def runs_result(tmp_path_factory, tiny_dir):
    out = tmp_path_factory.mktemp("runs")
    return out, run_worker("runs", out, tiny_dir)


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
    assert r["resumed2_chunks"] == 4
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
