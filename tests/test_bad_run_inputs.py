"""Run directories under careless or hostile use: two trainings in one directory, copied
and moved runs, fresh runs into existing directories, corrupt checkpoints, resumes that
would duplicate logs, and user errors that must be one line (exit code 2). Every case
checks that nothing that existed before was changed or deleted."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from orgnav_jax import train as train_cli
from orgnav_jax.errors import run_cli
from orgnav_jax.training import loop
from orgnav_jax.training.config import load_config
from orgnav_jax.training.run_dir import LOCK_FILE, RunLock

from helpers import CHUNK, poison_chunk, small_cfg, small_options



def argv_of(tiny_dir, run_dir, **kw) -> list[str]:
    """The CLI options of small_cfg(...), ending the run without a test evaluation."""
    argv = ["--preset", "tiny", "--no-test", "--quiet"]
    for k, v in small_options(tiny_dir, run_dir, **kw).items():
        argv += ["--" + k.replace("_", "-"), str(v)]
    return argv


def snapshot(path: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under `path` (directories as '<dir>')."""
    out = {}
    for p in sorted(Path(path).rglob("*")):
        rel = str(p.relative_to(path))
        out[rel] = "<dir>" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def records(run_dir) -> list[tuple]:
    return [(r["kind"], r["env_steps"]) for r in
            map(json.loads, (Path(run_dir) / "metrics.jsonl").read_text().splitlines())]


@pytest.fixture(scope="module")
def full_run(tmp_path_factory, tiny_dir):
    """An uninterrupted 4-chunk run: the reference for every resumed one."""
    run_dir = tmp_path_factory.mktemp("full") / "run"
    out = loop.train(small_cfg(tiny_dir, run_dir), progress=False)
    return run_dir, out["runner"]


@pytest.fixture(scope="module")
def half_run(tmp_path_factory, tiny_dir):
    """The same run stopped after 2 of its 4 chunks (checkpoints 256 and 512)."""
    run_dir = tmp_path_factory.mktemp("half") / "run"
    loop.train(small_cfg(tiny_dir, run_dir), progress=False, stop_after_chunks=2)
    return run_dir


def copy_of(run_dir: Path, where: Path) -> Path:
    shutil.copytree(run_dir, where)
    return where


# 2. two trainings into one run directory ------------------------------------------------

def test_a_run_directory_in_use_is_refused_and_a_stale_lock_taken_over(
        tmp_path, tiny_dir, half_run, full_run, cli_error, capsys):
    run = copy_of(half_run, tmp_path / "run")
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from orgnav_jax.training.run_dir import RunLock; "
        f"RunLock({str(run)!r}).acquire(); print('locked', flush=True); time.sleep(120)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        before = snapshot(run)
        msg = cli_error(train_cli.main, ["--run-dir", run, "--resume", "--quiet", "--no-test"])
        assert f"is in use by process {holder.pid} on {socket.gethostname()}" in msg
        assert str(run / LOCK_FILE) in msg
        assert snapshot(run) == before
        # the same process holding it (a second training in one program) is refused too
        with RunLock(tmp_path / "other"):
            msg = cli_error(train_cli.main, argv_of(tiny_dir, tmp_path / "other"))
            assert "is in use by process" in msg
    finally:
        holder.kill()
        holder.wait()
    # the holder is gone (killed: its lock file stays): the next resume takes it over
    assert (run / LOCK_FILE).exists()
    assert run_cli(train_cli.main, ["--run-dir", str(run), "--resume", "--quiet",
                                    "--no-test"]) == 0
    assert "took over the lock of process" in capsys.readouterr().err
    assert not (run / LOCK_FILE).exists()          # released at the end
    for a, b in zip(leaves(full_run[1].params), leaves(_restore(run).params)):
        np.testing.assert_array_equal(a, b)


def _restore(run_dir):
    from orgnav_jax.models import build_model
    from orgnav_jax.training.checkpoints import RunCheckpoints
    from orgnav_jax.training.runs import scenes_for
    from orgnav_jax.training.update import init_runner, make_optimizer
    cfg = load_config(run_dir)
    scenes = scenes_for(cfg).split_view("train").to_device()
    model = build_model(cfg, scenes)
    like = init_runner(cfg, model, make_optimizer(cfg), scenes, jax.random.PRNGKey(0))
    return RunCheckpoints(run_dir).restore(like)[0]


# 3. a copied or moved run resumes where it is ------------------------------------------

def test_a_copied_run_resumes_in_the_copy_and_a_moved_run_resumes(tmp_path, half_run,
                                                                 full_run):
    original = copy_of(half_run, tmp_path / "A")
    before = snapshot(original)
    copy = copy_of(original, tmp_path / "B")
    assert run_cli(train_cli.main, ["--run-dir", str(copy), "--resume", "--quiet",
                                    "--no-test"]) == 0
    assert snapshot(original) == before                       # the original is untouched
    assert load_config(copy).run_dir == str(copy)
    assert records(copy) == records(full_run[0])
    moved = tmp_path / "moved"
    os.rename(copy_of(original, tmp_path / "C"), moved)
    summary = train_cli.main(["--run-dir", str(moved), "--resume", "--quiet", "--no-test"])
    assert summary["chunks"] == 4 and summary["run_dir"] == str(moved)
    for a, b in zip(leaves(full_run[1].params), leaves(_restore(moved).params)):
        np.testing.assert_array_equal(a, b)
    assert snapshot(original) == before


# 4. a fresh run into an existing run or into someone's files ---------------------------

def test_a_fresh_run_never_writes_into_an_existing_directory(tmp_path, tiny_dir, half_run,
                                                             cli_error):
    # a run that crashed before its first checkpoint: config.json and logs, no checkpoints
    crashed = copy_of(half_run, tmp_path / "crashed")
    shutil.rmtree(crashed / "checkpoints")
    (crashed / "checkpoints").mkdir()
    theirs = tmp_path / "thesis"
    (theirs / "figures").mkdir(parents=True)
    (theirs / "thesis.txt").write_text("four years of work")
    for run_dir, expect in ((crashed, "already holds a run: pass --resume"),
                            (half_run, "already holds a run: pass --resume"),
                            (theirs, "is a non-empty directory that is not a run")):
        before = snapshot(run_dir)
        msg = cli_error(train_cli.main, argv_of(tiny_dir, run_dir, seed=1))
        assert expect in msg and str(run_dir) in msg
        assert snapshot(run_dir) == before
    msg = cli_error(train_cli.main, ["--run-dir", theirs, "--resume"])
    assert "is not a training run directory" in msg
    assert (theirs / "thesis.txt").read_text() == "four years of work"


# 6. a corrupt newest checkpoint ---------------------------------------------------------

def _drop_state_metadata(step: Path) -> None:
    (step / "state" / "_METADATA").unlink()


def _truncate_largest_array(step: Path) -> None:
    biggest = max((f for f in (step / "state").rglob("*") if f.is_file()),
                  key=lambda f: f.stat().st_size)
    data = biggest.read_bytes()
    biggest.write_bytes(data[: len(data) // 2])


def _garble_meta(step: Path) -> None:
    (step / "meta" / "metadata").write_text("{garbled")


@pytest.mark.parametrize("damage", [_drop_state_metadata, _truncate_largest_array,
                                    _garble_meta])
def test_a_corrupt_newest_checkpoint_is_named_set_aside_and_resume_falls_back(
        tmp_path, tiny_dir, half_run, full_run, damage, capsys):
    run = copy_of(half_run, tmp_path / "run")
    newest = run / "checkpoints" / str(2 * CHUNK)
    damage(newest)
    broken = snapshot(newest)
    capsys.readouterr()
    out = loop.train(small_cfg(tiny_dir, run), resume=True, progress=False)
    err = capsys.readouterr().err
    assert f"checkpoint {newest}" in err and f"resumed from step {CHUNK}" in err
    # the notice and nothing else (no echoes of orbax's failed reader threads)
    assert "Traceback" not in err and "Event loop is closed" not in err and \
        "Exception ignored" not in err, err[:2000]
    aside = run / "broken_checkpoints" / str(2 * CHUNK)
    assert snapshot(aside) == broken                        # kept, byte for byte
    for a, b in zip(leaves(full_run[1]), leaves(out["runner"])):
        np.testing.assert_array_equal(a, b)
    assert records(run) == records(full_run[0])


def test_the_fallback_prints_its_notice_and_nothing_else(tmp_path, half_run):
    """As a user sees it (a separate process, no pytest hooks): resuming past a truncated
    checkpoint prints the run line, one warning and the summary, no thread tracebacks."""
    import subprocess
    import sys
    run = copy_of(half_run, tmp_path / "run")
    _truncate_largest_array(run / "checkpoints" / str(2 * CHUNK))
    done = subprocess.run([sys.executable, "-m", "orgnav_jax.train", "--run-dir", str(run),
                           "--resume", "--quiet", "--no-test"], capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("warning: checkpoint "), done.stderr[:3000]


def test_the_asyncio_echo_of_a_dead_read_task_is_dropped_and_other_records_kept():
    """A task or future of orbax's reads may be collected after the fallback is over;
    asyncio then logs "Task (or Future) exception was never retrieved" (each seen once in
    a full run). The logger's filter drops those records and keeps every other one."""
    import logging
    from orgnav_jax.training import checkpoints

    def record(msg, exc=None):
        info = (type(exc), exc, exc.__traceback__) if exc else None
        return logging.LogRecord("asyncio", logging.ERROR, __file__, 1, msg, None, info)
    echo = record("Task exception was never retrieved\nfuture: <Task finished coro=<"
                  "async_deserialize() done, defined at /site-packages/orbax/checkpoint/"
                  "_src/serialization/serialization.py:394>>", Exception("reading array"))
    other = record("Task exception was never retrieved\nfuture: <Task coro=<mine()>>",
                   RuntimeError("a user's own task"))
    # a tensorstore read future has no Python traceback; its error names the OCDBT file
    # (seen once in a full run: the subprocess fallback test printed 7 lines)
    error = ('OUT_OF_RANGE: Error reading "carry.0.1/0.0" in OCDBT database at local file '
             '"/tmp/run/checkpoints/512/state/": Requested byte range [3323942, 3331611) '
             'is not valid for value of size 1795197')
    future = record("Future exception was never retrieved\nfuture: <Future finished "
                    f"exception=ValueError({error!r})>", ValueError(error))
    assert checkpoints._not_a_read_echo(echo) is False
    assert checkpoints._not_a_read_echo(future) is False
    assert checkpoints._not_a_read_echo(other) is True
    checkpoints._drop_read_echoes()
    assert checkpoints._not_a_read_echo in logging.getLogger("asyncio").filters


def test_no_readable_checkpoint_is_an_error_that_moves_nothing(tmp_path, tiny_dir, half_run,
                                                               cli_error):
    run = copy_of(half_run, tmp_path / "run")
    for step in (run / "checkpoints").iterdir():
        _garble_meta(step)
    before = snapshot(run)
    msg = cli_error(train_cli.main, ["--run-dir", run, "--resume", "--quiet", "--no-test"])
    assert f"checkpoint {run / 'checkpoints' / str(2 * CHUNK)} cannot be read" in msg
    assert snapshot(run) == before


# 9. no duplicated metrics records after a resume ----------------------------------------

def test_resume_rewrites_no_metrics_record_twice(tmp_path, tiny_dir, full_run):
    run = tmp_path / "run"
    cfg = small_cfg(tiny_dir, run, checkpoint_every_chunks=2)
    loop.train(cfg, progress=False, stop_after_chunks=3)        # killed after chunk 3
    assert ("train", 3 * CHUNK) in records(run)                 # logged, not checkpointed
    loop.train(cfg, resume=True, progress=False)
    assert records(run) == records(full_run[0])


# 10. user errors are one line with exit code 2 -----------------------------------------

def test_user_errors_of_train_are_one_line(tmp_path, tiny_dir, cli_error):
    msg = cli_error(train_cli.main, argv_of(tmp_path / "no-scenes", tmp_path / "r1"))
    assert "no-scenes" in msg and "does not exist" in msg
    msg = cli_error(train_cli.main, ["--scene-preset", "huge", "--run-dir", tmp_path / "r2"])
    assert "huge" in msg
    assert not (tmp_path / "r1").exists() and not (tmp_path / "r2").exists()


def test_a_non_finite_loss_is_a_one_line_error_that_keeps_the_checkpoints(
        tmp_path, tiny_dir, monkeypatch, cli_error):
    poison_chunk(monkeypatch, at=3)
    msg = cli_error(train_cli.main, argv_of(tiny_dir, tmp_path / "run"))
    assert "non-finite loss in chunk 3" in msg
    assert sorted(p.name for p in (tmp_path / "run" / "checkpoints").iterdir()) == \
        [str(CHUNK), str(2 * CHUNK)]
    assert not (tmp_path / "run" / LOCK_FILE).exists()


def test_debug_shows_the_traceback(tmp_path):
    with pytest.raises(FileNotFoundError):
        run_cli(train_cli.main, ["--run-dir", str(tmp_path / "none"), "--resume", "--debug"])


# 11. typed readers of what a run reads back (issue 22) ---------------------------------

def _edit_meta(step_dir: Path, **fields) -> None:
    path = step_dir / "meta" / "metadata"
    meta = json.loads(path.read_text())
    meta.update(fields)
    path.write_text(json.dumps(meta))


@pytest.mark.parametrize("chunk", [1_000_000, 1, 0])
def test_a_checkpoint_chunk_the_run_never_reached_is_refused(tmp_path, half_run, chunk,
                                                            cli_error):
    run = copy_of(half_run, tmp_path / "run")
    newest = run / "checkpoints" / str(2 * CHUNK)
    _edit_meta(newest, chunk=chunk)
    before = snapshot(run)
    msg = cli_error(train_cli.main, ["--run-dir", run, "--resume", "--quiet", "--no-test"])
    assert msg == (f"error: checkpoint {newest} metadata: field 'chunk': expected 2 (its step "
                   f"{2 * CHUNK} / {CHUNK} steps per chunk; the run has 4 chunks), got {chunk}")
    assert snapshot(run) == before


@pytest.mark.parametrize("fields, message", [
    (dict(chunk="2"), "field 'chunk': expected an integer 0 <= chunk <= 2,147,483,647, got '2'"),
    (dict(chunk=None), "field 'chunk': expected an integer 0 <= chunk <= 2,147,483,647, got None"),
    (dict(chunk=2 ** 40), "field 'chunk': expected an integer 0 <= chunk <= 2,147,483,647, got "
                          "1099511627776"),
    (dict(best=[1, 2]), "field 'best': expected an object of numbers (val metric -> value), "
                        "got a list"),
    (dict(best={"success": "0.5", "spl": 0.1}), "'best': field 'success': expected a number, "
                                                "got '0.5'"),
    (dict(config_version=True), "has config version True, expected one of [2, 3, 4, 5, 6, 7, 8, 9]"),
])
def test_malformed_checkpoint_metadata_is_named_and_set_aside(tmp_path, tiny_dir, half_run,
                                                              fields, message, capsys):
    """Metadata of the wrong types makes a checkpoint unreadable: named, moved aside
    (kept), and the resume falls back to the previous one, as for a damaged checkpoint."""
    run = copy_of(half_run, tmp_path / "run")
    newest = run / "checkpoints" / str(2 * CHUNK)
    _edit_meta(newest, **fields)
    from orgnav_jax.training.checkpoints import CheckpointUnreadable
    with pytest.raises(CheckpointUnreadable) as err:
        _restore(run)
    assert str(err.value).startswith(f"checkpoint {newest}") and message in str(err.value)
    capsys.readouterr()
    loop.train(small_cfg(tiny_dir, run), resume=True, progress=False, stop_after_chunks=2)
    err = capsys.readouterr().err
    assert message in err and f"resumed from step {CHUNK}" in err
    assert (run / "broken_checkpoints" / str(2 * CHUNK)).is_dir()


@pytest.mark.parametrize("line, message", [
    ('{"kind": "train", "env_steps": "256"}', "field 'env_steps': expected an integer "
                                              "env_steps >= 0, got '256'"),
    ('{"kind": "val", "env_steps": 256, "success": null}', "field 'success': expected a "
                                                           "number, got None"),
    ('["train", 256]', "expected a JSON object {kind, env_steps, metric: number}, got a list"),
    ('{"env_steps": 256}', "field 'kind' is missing"),
])
def test_a_malformed_metrics_jsonl_is_one_line_and_resume_writes_nothing(
        tmp_path, half_run, line, message, cli_error):
    from orgnav_jax.plots import CurveError, read_val_curve
    run = copy_of(half_run, tmp_path / "run")
    log = run / "metrics.jsonl"
    n = len(log.read_text().splitlines()) + 1
    with log.open("a") as f:
        f.write(line + "\n")
    before = snapshot(run)
    msg = cli_error(train_cli.main, ["--run-dir", run, "--resume", "--quiet", "--no-test"])
    assert msg == f"error: {log} line {n}: {message}"
    assert snapshot(run) == before
    with pytest.raises(CurveError, match=re.escape(f"{log} line {n}: {message}")):
        read_val_curve(run, ["success"])


def test_checkpoints_on_scenes_of_other_feature_widths_are_refused_before_a_model_is_built(
        tmp_path, tiny_dir, half_run, cli_error, monkeypatch):
    from orgnav_jax import evaluate
    from orgnav_jax import scenes as S
    from orgnav_jax.models import navmodel
    full = S.load(tiny_dir)
    narrow = tmp_path / "narrow"
    S.save(full.replace(global_basis=np.asarray(full.global_basis)[:, :8]), narrow)
    run = copy_of(half_run, tmp_path / "run")
    before = snapshot(tmp_path)

    def no_model(*a, **kw):
        raise AssertionError("a model was built")
    monkeypatch.setattr(navmodel, "NavModel", no_model)
    # the run's scenes replaced by narrower ones (a moved run resumed with --scenes-dir)
    msg = cli_error(train_cli.main, ["--run-dir", run, "--resume", "--scenes-dir", narrow,
                                     "--quiet", "--no-test"])
    assert msg == (f"error: checkpoint {run / 'checkpoints' / str(2 * CHUNK)} was trained on "
                   f"scene features of global_dim 16, but scenes {narrow} have global_dim 8: "
                   "use scenes with the feature widths the model was trained on")
    text = (run / "config.json").read_text()
    (run / "config.json").write_text(json.dumps({**json.loads(text),
                                                 "scenes_dir": str(narrow)}))
    with pytest.raises(ValueError, match=rf"checkpoint {re.escape(str(run / 'best'))}/\d+ was "
                                         r"trained on scene features of global_dim 16, but "
                                         rf"scenes {re.escape(str(narrow))} have global_dim 8"):
        loop_runs().load_run_model(run)
    (run / "config.json").write_text(text)
    monkeypatch.undo()
    # evaluating the run's model on other scenes: refused before anything is compiled
    msg = cli_error(evaluate.main, ["--checkpoint", run, "--scenes", narrow, "--split", "val",
                                    "--quiet", "--out", tmp_path / "res.json"])
    assert msg.startswith("error: policy baseline was trained on scene features of "
                          "global_dim 16, but scenes (4 rooms of preset 'tiny') have "
                          "global_dim 8")
    assert not (tmp_path / "res.json").exists()
    after = {k: v for k, v in snapshot(tmp_path).items() if not k.startswith("episodes-")}
    assert after == before          # (the sampled episode file is written before it)


def loop_runs():
    from orgnav_jax.training import runs
    return runs


# round five (issue 67): runs made before the default scene preset changed ----------------

def test_a_config_without_its_scene_preset_is_refused_not_read_as_todays_default(
        tmp_path, half_run, cli_error):
    """A config.json without scene_preset (the default was `small` when it was implicit)
    was evaluated and resumed on today's default, `calibrated`, without a word."""
    from orgnav_jax import evaluate
    run = copy_of(half_run, tmp_path / "run")
    doc = json.loads((run / "config.json").read_text())
    del doc["scene_preset"]
    (run / "config.json").write_text(json.dumps(doc))
    before = snapshot(tmp_path)
    want = (f"error: {run / 'config.json'}: field 'scene_preset' is missing: expected the "
            "scene preset the run was trained on (this program writes it in every run's "
            "config; the default was 'small' before 2026-12-05 and is 'calibrated' since): "
            'add it, e.g. "scene_preset": "small"')
    assert cli_error(evaluate.main, ["--checkpoint", run, "--split", "val", "--quiet",
                                     "--out", tmp_path / "res.json"]) == want
    assert cli_error(train_cli.main, ["--run-dir", run, "--resume", "--quiet",
                                      "--no-test"]) == want
    assert snapshot(tmp_path) == before


def test_evaluate_a_run_on_another_scene_preset_says_so(tmp_path, half_run, tiny_scenes,
                                                        tiny_dir, cli_error, capsys,
                                                        monkeypatch):
    """`evaluate --checkpoint RUN --scene-preset X` evaluated on the run's own scenes and
    ignored X; it now evaluates on X (as --scenes does) with a note naming both, the
    results record X; --scene-preset with --scenes is one line."""
    from orgnav_jax import evaluate
    from orgnav_jax import scenes as S
    from orgnav_jax.scenes.synthetic import cache
    monkeypatch.setenv("ORGNAV_CACHE", str(tmp_path / "cache"))
    S.save(tiny_scenes, cache.cache_path("tiny", 0))      # preset tiny, without building it
    run = copy_of(half_run, tmp_path / "run")
    before = snapshot(run)
    msg = cli_error(evaluate.main, ["--checkpoint", run, "--scene-preset", "tiny",
                                    "--scenes", tiny_dir, "--quiet"])
    assert msg == f"error: --scene-preset tiny and --scenes {tiny_dir}: give one (the " \
                  "scenes to evaluate on)"
    capsys.readouterr()
    out = tmp_path / "res.json"
    result = evaluate.main(["--checkpoint", str(run), "--scene-preset", "tiny", "--split",
                            "val", "--episodes-per-room-type", "2", "--quiet", "--out",
                            str(out)])
    err = capsys.readouterr().err
    assert f"note: {run} was trained on scenes {tiny_dir}; evaluating it on scene preset " \
           "tiny, as --scene-preset asks" in err, err
    assert result["scenes"] == "tiny" and json.loads(out.read_text())["scenes"] == "tiny"
    assert snapshot(run) == before
    cache.clear_loaded()


def test_reading_a_run_without_checkpoints_is_one_line_and_creates_nothing(
        tmp_path, half_run, cli_error):
    """A run whose checkpoints are gone (a new checkout: they stay out of git): evaluating
    it names the run, and the read makes no empty checkpoints/ or best/ folder."""
    from orgnav_jax import evaluate
    run = copy_of(half_run, tmp_path / "run")
    for sub in ("checkpoints", "best"):
        shutil.rmtree(run / sub)
    before = snapshot(run)
    msg = cli_error(evaluate.main, ["--checkpoint", run, "--split", "val",
                                    "--episodes-per-room-type", "2", "--quiet"])
    assert msg == f"error: no checkpoint in {run}", msg
    assert snapshot(run) == before
