"""experiments/gpu_streams/pack.py: what comes back from a GPU machine, on a hand-made
/tmp/g (streams of table rows and a command stream)."""

from __future__ import annotations

import importlib.util
import json
import tarfile
from pathlib import Path

PACK = Path(__file__).resolve().parents[1] / "experiments" / "gpu_streams" / "pack.py"


def make_run(run: Path, steps: int, tested: bool, best: bool = False,
             budget: int = 1000) -> None:
    (run / "checkpoints" / str(steps)).mkdir(parents=True)
    (run / "checkpoints" / str(steps) / "state").write_bytes(b"x" * 100)
    if best:
        (run / "best" / str(steps)).mkdir(parents=True)
        (run / "best" / str(steps) / "state").write_bytes(b"b" * 100)
    (run / "config.json").write_text(json.dumps({"total_env_steps": budget}))
    (run / "metrics.jsonl").write_text(json.dumps({"kind": "train", "env_steps": steps}) + "\n")
    if tested:
        (run / "test_results.json").write_text("{}")


def test_pack_brings_back_small_files_tpn_bases_and_the_runs_that_can_go_on(
        tmp_path, monkeypatch):
    """small.tgz: every run's small files (no checkpoints) and the streams' records, a
    command stream's sweep record included; best_ROW.tar: a finished row a TPN row builds
    on; part_runs.tar: the runs that can go on elsewhere, most advanced first, as many as
    fit: a row's run trained but not tested (its best checkpoint only), a run short of
    its budget (latest checkpoints, a command stream's too); the least advanced that
    does not fit is left out."""
    spec = importlib.util.spec_from_file_location("pack", PACK)
    pack = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pack)
    g, out = tmp_path / "g", tmp_path / "out"
    out.mkdir()
    monkeypatch.setattr(pack, "STREAMS", g)
    for i, rows in ((1, ["baseline", "baseline+tpn@1e-4"]), (3, ["il", "org"])):
        (g / f"out{i}").mkdir(parents=True)
        (g / f"spec{i}.json").write_text(json.dumps({"rows": rows}))
    for s in (0, 1):
        make_run(g / "out1" / "runs" / f"baseline-s{s}", 1000, tested=True, best=True)
        make_run(g / "out3" / "runs" / f"il-s{s}", 300, tested=False)
    make_run(g / "out3" / "runs" / "org-s0", 1000, tested=False, best=True)  # trained
    make_run(g / "out3" / "runs" / "org-s1", 200, tested=False)
    make_run(g / "out2" / "runs" / "vt-s100", 900, tested=False)      # a `cmd:` stream
    (g / "out2" / "vt.json").write_text("{}")
    (g / "log2.txt").write_text("log")
    # room for four runs' checkpoints (100_000 bytes of headers reserved per directory)
    monkeypatch.setattr(pack, "TOTAL_LIMIT", 460_000)
    pack.main(out)
    assert sorted(p.name for p in out.iterdir()) == ["best_baseline.tar", "part_runs.tar",
                                                     "small.tgz"]
    with tarfile.open(out / "small.tgz") as t:
        names = set(t.getnames())
    assert {"runs/baseline-s0/test_results.json", "runs/vt-s100/metrics.jsonl",
            "meta/out2-vt.json", "meta/g-log2.txt"} <= names
    assert not [n for n in names if "checkpoints" in n or "best" in n.split("/")]
    with tarfile.open(out / "best_baseline.tar") as t:
        assert "runs/baseline-s1/best/1000/state" in t.getnames()
    with tarfile.open(out / "part_runs.tar") as t:
        names = {n for n in t.getnames() if n.endswith("/state")}
    assert names == {"runs/org-s0/best/1000/state", "runs/vt-s100/checkpoints/900/state",
                     "runs/il-s0/checkpoints/300/state", "runs/il-s1/checkpoints/300/state"}


def test_run_sh_without_its_arguments_is_one_line_and_usage_exit_2(tmp_path):
    """Issue 55: `bash experiments/gpu_streams/run.sh` with no arguments died on an unbound
    variable: every argument and OUT is checked first; a usage line, one `error:` line,
    exit 2, nothing written or started."""
    import os
    import subprocess
    run_sh = PACK.with_name("run.sh")
    env = {k: v for k, v in os.environ.items() if k not in ("OUT", "SPEC")}
    (tmp_path / "file").write_text("mine")
    cases = [
        ([], {}, "expected DEADLINE_S, COMMIT and at least one stream, got 0 argument(s)"),
        (["60", "abc"], {}, "got 2 argument(s)"),
        (["soon", "abc", "baseline"], {"OUT": str(tmp_path / "o")}, "DEADLINE_S 'soon'"),
        (["60", "", "baseline"], {"OUT": str(tmp_path / "o")}, "COMMIT is empty"),
        (["60", "abc", "baseline"], {}, "OUT is not set"),
        (["60", "abc", "baseline"], {"OUT": str(tmp_path / "file")}, "is not a directory"),
        (["60", "abc", "baseline"], {"OUT": str(tmp_path / "o"), "SPEC": str(tmp_path / "s")},
         "SPEC " + str(tmp_path / "s") + ": no such file"),
        (["60", "abc", " "], {"OUT": str(tmp_path / "o")}, "a stream is empty"),
    ]
    for argv, extra, message in cases:
        done = subprocess.run(["bash", str(run_sh), *argv], env={**env, **extra},
                              capture_output=True, text=True, cwd=tmp_path, timeout=60)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2, (argv, done.stderr)
        assert len(lines) == 2 and lines[0].startswith("usage: ") and \
            lines[1].startswith("error: ") and message in lines[1], (argv, done.stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
