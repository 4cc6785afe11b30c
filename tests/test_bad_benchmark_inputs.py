"""The benchmark scripts under bad input (issue 67): a tree or a commit without the env
for env_versions.py, an unknown preset for scene_build.py, a --num-envs beyond int32 for
train_throughput.py: argparse's one-line `error: ...` and exit code 2 before any work
(no worktree made, nothing built or timed)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from orgnav_jax.scenes.synthetic.presets import SCENE_PRESETS

ROOT = Path(__file__).resolve().parents[1]


def bench(name: str):
    """benchmarks/<name>.py loaded as a module (the scripts are not a package)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" /
                                                  f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module                 # its dataclasses look it up
    spec.loader.exec_module(module)
    return module


def error_of(main, argv: list[str], monkeypatch, capsys) -> str:
    """The one `error:` line of a script's main() given argv (exit code 2)."""
    monkeypatch.setattr(sys, "argv", ["script", *argv])
    capsys.readouterr()
    with pytest.raises(SystemExit) as done:
        main()
    err = capsys.readouterr().err
    assert done.value.code == 2, err
    assert "Traceback" not in err
    return [line for line in err.splitlines() if line.strip()][-1]


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_env_versions_refuses_a_tree_and_a_commit_without_the_env(monkeypatch, capsys):
    ev = bench("env_versions")
    worktrees = git("worktree", "list")
    line = error_of(ev.main, ["HEAD^{tree}"], monkeypatch, capsys)
    assert line.endswith(f"error: 'HEAD^{{tree}}' is a tree in {ROOT}, expected a commit")
    line = error_of(ev.main, ["no-such-commit"], monkeypatch, capsys)
    assert line.endswith("'no-such-commit' names nothing in " f"{ROOT}, expected a commit")
    root = git("rev-list", "--max-parents=0", "HEAD").split()[0]     # before the env
    line = error_of(ev.main, [root], monkeypatch, capsys)
    assert "has no module orgnav_jax.env" in line and "expected a commit with the env" in line
    assert git("worktree", "list") == worktrees          # no worktree was made


def test_scene_build_refuses_an_unknown_preset_before_building(monkeypatch, capsys):
    sb = bench("scene_build")

    def no_build(*a, **kw):
        raise AssertionError("a preset was built")
    monkeypatch.setattr(sb.scenes, "build", no_build)
    line = error_of(sb.main, ["--presets", "tiny", "smal"], monkeypatch, capsys)
    assert line.endswith(f"error: unknown scene preset 'smal': expected one of "
                         f"{sorted(SCENE_PRESETS)}"), line
    assert "raw features" in error_of(sb.main, ["--presets", "large"], monkeypatch, capsys)
    assert "--seed -1" in error_of(sb.main, ["--seed", "-1"], monkeypatch, capsys)


def test_train_throughput_refuses_a_num_envs_beyond_int32_before_timing(monkeypatch, capsys):
    tt = bench("train_throughput")

    def no_timing(*a, **kw):
        raise AssertionError("the benchmark started")
    monkeypatch.setattr(tt, "matmul_peak_gflops", no_timing)
    line = error_of(tt.main, ["--models", "baseline", "--presets", "small", "--num-envs",
                              "16", "3000000000"], monkeypatch, capsys)
    assert line.endswith("error: config field 'num_envs': 3000000000, expected an integer "
                         "num_envs >= 1 and at most 2,147,483,647 (int32)"), line
