"""The trainer: losses, resume, checkpoints, NaN handling, compile count, bad input,
and (slow) a learning test on unseen rooms."""

from __future__ import annotations

import dataclasses
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import scenes as scenes_mod
from orgnav_jax.training import loop
from orgnav_jax.training.checkpoints import RunCheckpoints
from orgnav_jax.training.driver import NonFiniteLoss
from orgnav_jax.training.config import get_config, load_config
from orgnav_jax.training.losses import gae
from orgnav_jax.training.runs import load_run_policy

from helpers import poison_chunk, small_cfg, trained_and_random_success


def leaves(tree):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def test_gae_matches_a_hand_computation():
    reward = jnp.array([[1.0], [0.0], [2.0]])
    value = jnp.array([[0.5], [0.2], [0.1]])
    done = jnp.array([[False], [True], [False]])
    adv, ret = gae(reward, value, done, jnp.array([0.3]), gamma=0.9, lam=0.5)
    d2 = 2.0 + 0.9 * 0.3 - 0.1
    d1 = 0.0 - 0.2                         # episode ends after step 1: no bootstrap
    d0 = 1.0 + 0.9 * 0.2 - 0.5
    expect = [d0 + 0.45 * d1, d1, d2]
    np.testing.assert_allclose(np.asarray(adv)[:, 0], expect, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(ret), np.asarray(adv) + np.asarray(value))


def test_kill_and_resume_equals_an_uninterrupted_run(tmp_path, tiny_dir):
    full = loop.train(small_cfg(tiny_dir, tmp_path / "full"), progress=False)
    cfg = small_cfg(tiny_dir, tmp_path / "killed")
    first = loop.train(cfg, progress=False, stop_after_chunks=2)
    assert first["chunks"] == 2
    with pytest.raises(FileExistsError, match="--resume"):
        loop.train(cfg, progress=False)
    resumed = loop.train(cfg, resume=True, progress=False)
    assert resumed["chunks"] == 4
    for a, b in zip(leaves(full["runner"]), leaves(resumed["runner"])):
        np.testing.assert_array_equal(a, b)
    log = [json.loads(line) for line in (tmp_path / "killed" / "metrics.jsonl").open()]
    assert [r["env_steps"] for r in log if r["kind"] == "train"] == [256, 512, 768, 1024]


def test_a_resume_without_checkpoints_says_it_starts_again(tmp_path, tiny_dir, capsys):
    """Killed before its first checkpoint, or its checkpoints lost: the resume trains
    from step 0, says so, and its log holds each step once. After its second val
    evaluation the run estimates its time with evaluations and checkpoints."""
    cfg = small_cfg(tiny_dir, tmp_path / "run", eval_every_chunks=1)
    loop.train(cfg, progress=False, stop_after_chunks=2)
    shutil.rmtree(tmp_path / "run" / "checkpoints")
    capsys.readouterr()
    loop.train(cfg, resume=True, progress=False)
    err = capsys.readouterr().err
    assert (f"train baseline: resume: no checkpoint in {tmp_path / 'run' / 'checkpoints'}; "
            f"training starts again from step 0 (its metrics.jsonl's") in err, err
    assert ("steps/s with evaluations and checkpoints, over chunks 2-2: the remaining 2 of "
            "4 chunks take about") in err, err
    log = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").open()]
    assert [r["env_steps"] for r in log if r["kind"] == "train"] == [256, 512, 768, 1024]


def test_resume_may_extend_the_budget_to_match_a_longer_run(tmp_path, tiny_dir):
    """A finished 2-chunk run resumed with a 4-chunk budget (the old budget ended on an
    evaluation chunk) equals a 4-chunk run; a smaller budget or other options are refused."""
    full = loop.train(small_cfg(tiny_dir, tmp_path / "full"), progress=False)
    short = small_cfg(tiny_dir, tmp_path / "short", total_env_steps=16 * 8 * 2 * 2)
    loop.train(short, progress=False)
    longer = small_cfg(tiny_dir, tmp_path / "short")
    resumed = loop.train(longer, resume=True, progress=False)
    for a, b in zip(leaves(full["runner"]), leaves(resumed["runner"])):
        np.testing.assert_array_equal(a, b)
    assert load_config(tmp_path / "short").total_env_steps == longer.total_env_steps
    with pytest.raises(ValueError, match="may only extend the budget"):
        loop.train(short, resume=True, progress=False)
    with pytest.raises(ValueError, match="differs from the requested config"):
        loop.train(small_cfg(tiny_dir, tmp_path / "short", lr=1e-3), resume=True,
                   progress=False)


def test_interrupted_save_leaves_the_previous_checkpoint_loadable(tmp_path, tiny_dir):
    cfg = small_cfg(tiny_dir, tmp_path / "run")
    out = loop.train(cfg, progress=False, stop_after_chunks=2)
    ckpt_dir = tmp_path / "run" / "checkpoints"
    # what a save killed half-way leaves: orbax's temporary directory, never renamed
    partial = ckpt_dir / "99999.orbax-checkpoint-tmp-1234567"
    (partial / "state").mkdir(parents=True)
    (partial / "state" / "garbage").write_bytes(b"\x00" * 10)
    ckpt = RunCheckpoints(tmp_path / "run")
    assert ckpt.latest_step() == 512
    restored, meta = ckpt.restore(out["runner"])
    assert meta["chunk"] == 2
    for a, b in zip(leaves(out["runner"]), leaves(restored)):
        np.testing.assert_array_equal(a, b)


def test_nan_loss_stops_with_a_clear_message_and_keeps_the_last_checkpoint(
        tmp_path, tiny_dir, monkeypatch):
    poison_chunk(monkeypatch, at=3, nan_params=True)
    cfg = small_cfg(tiny_dir, tmp_path / "run")
    with pytest.raises(NonFiniteLoss, match="non-finite loss in chunk 3.*last good "
                                                 "checkpoint"):
        loop.train(cfg, progress=False)
    ckpt = RunCheckpoints(tmp_path / "run")
    assert ckpt.latest_step() == 512
    _, params, _ = load_run_policy(tmp_path / "run", best=False)
    assert all(np.isfinite(x).all() for x in leaves(params))


@pytest.mark.parametrize("extra", [{}, dict(il="deadlock", il_step="cause", dropout=0.25)])
def test_train_chunk_compiles_once(tmp_path, tiny_dir, extra):
    """Chunks after the first reuse its program. The trainer's cached chunk is used (the
    program the other runs of this computation in the process share), so the first call
    may find it compiled already: the count must not grow after it."""
    cfg = small_cfg(tiny_dir, tmp_path / "run", **extra)
    train = scenes_mod.load(tiny_dir).split_view("train").to_device()
    model = loop.build_model(cfg, train)
    optimizer, chunk = loop.cached_train_chunk(loop.compute_config(cfg), model)
    runner = loop.init_runner(cfg, model, optimizer, train, jax.random.PRNGKey(0))
    runner, _ = chunk(runner, train)
    compiled = chunk._cache_size()
    for _ in range(2):
        runner, _ = chunk(runner, train)
    assert compiled >= 1 and chunk._cache_size() == compiled
    assert int(runner.update) == 3 * cfg.updates_per_chunk
    assert all(np.isfinite(x).all() for x in leaves(runner.params))


def test_a_cached_factory_is_one_entry_however_the_call_is_spelled():
    """compiled_once keys on the bound arguments with defaults filled in: the scale-out
    worker called cached_train_chunk(cfg, model) where the trainer calls (cfg, model,
    None, False), and the same chunk compiled twice."""
    from orgnav_jax.compile_cache import compiled_once
    made = []

    @compiled_once
    def make(cfg, model, mesh=None, population=False):
        made.append((cfg, model, mesh, population))
        return object()

    first = make(1, 2)
    assert make(1, 2, None) is first and make(1, model=2, population=False) is first
    assert make(1, 2, population=True) is not first
    assert made == [(1, 2, None, False), (1, 2, None, True)]


def test_where_the_rooms_come_from_is_not_in_the_compile_key(tmp_path, tiny_dir):
    """Two copies of a scene set (another directory, another scene seed field, or the
    preset instead of a directory) give one cached program (the rooms are its input)."""
    a = small_cfg(tiny_dir, tmp_path / "a")
    b = small_cfg(tmp_path / "copy", tmp_path / "b", scene_seed=5)   # a path is only a path
    c = dataclasses.replace(a, scenes_dir=None, scene_preset="tiny")
    assert loop.compute_config(a) == loop.compute_config(b) == loop.compute_config(c)
    train = scenes_mod.load(tiny_dir).split_view("train").to_device()
    model = loop.build_model(a, train)
    assert loop.cached_train_chunk(loop.compute_config(a), model) is \
        loop.cached_train_chunk(loop.compute_config(b), model)
    # what the chunk reads is still in the key
    assert loop.compute_config(a) != loop.compute_config(small_cfg(tiny_dir, tmp_path / "a",
                                                                   num_envs=8))


def test_bad_config_and_checkpoints_are_clear_errors(tmp_path, tiny_dir, cli_error):
    with pytest.raises(ValueError, match="unknown training preset 'huge'"):
        get_config("huge")
    with pytest.raises(ValueError, match=r"unknown config field\(s\) \['learning_rate'\]"):
        get_config("small", learning_rate=1e-3)
    with pytest.raises(ValueError, match="config field 'model': unknown model 'resnet'"):
        get_config("small", model="resnet")
    cfg = small_cfg(tiny_dir, tmp_path / "run")
    loop.train(cfg, progress=False, stop_after_chunks=1)
    # a checkpoint from another model (other widths) does not load into this one
    other = small_cfg(tiny_dir, tmp_path / "run", hidden=32)
    with pytest.raises(ValueError, match=r"does not fit this model.*\(16, 128\) float32 in the "
                       r"checkpoint, \(16, 32\) float32 in this model"):
        _restore_as(other)
    # a run directory from an incompatible version
    path = tmp_path / "run" / "config.json"
    doc = json.loads(path.read_text())
    path.write_text(json.dumps(dict(doc, version=0)))
    with pytest.raises(ValueError, match="config version 0"):
        load_config(tmp_path / "run")
    with pytest.raises(FileNotFoundError, match="not a training run directory"):
        load_config(tmp_path / "nothing")
    # the command line reports the same errors and exits before any work
    from orgnav_jax import train as train_cli
    assert "unknown model 'resnet'" in cli_error(train_cli.main, ["--model", "resnet"])
    with pytest.raises(SystemExit):
        train_cli.main(["--preset", "huge"])


def _restore_as(cfg):
    train = scenes_mod.load(cfg.scenes_dir).split_view("train").to_device()
    model = loop.build_model(cfg, train)
    runner = loop.init_runner(cfg, model, loop.make_optimizer(cfg), train,
                              jax.random.PRNGKey(0))
    RunCheckpoints(cfg.run_dir).restore(runner)


@pytest.mark.slow
def test_trained_agent_beats_random_on_unseen_rooms(tmp_path, tiny_dir):
    """~1-3 minutes: the baseline trained on the 8 tiny training rooms succeeds at least 3x
    as often as random on the 4 unseen test rooms (fixed seed). 655,360 env steps (64
    chunks): at 400 k, the budget until 2026-12-04, an Intel Xeon (AVX-512) machine gave
    0.096 test success (random 0.032) where the AMD EPYC machines had given 0.22 on val;
    its val curve there: 0.125 at 410 k, 0.135-0.175 at 450-615 k, 0.32 at 655 k; 0.334
    test success at 809 k (docs/history/test-suite-time.md)."""
    cfg = get_config("tiny", scenes_dir=tiny_dir, run_dir=str(tmp_path / "run"),
                     total_env_steps=655_360)
    loop.train(cfg, progress=False)
    trained, rand = trained_and_random_success(tmp_path / "run", tiny_dir, "test")
    assert trained >= 3 * rand and trained > 0.1, (trained, rand)


def test_the_progress_bar_shows_the_last_val(tmp_path, tiny_dir, capsys, monkeypatch):
    """The bar's best_val is refreshed after the chunk's val evaluation, so its last value
    is the run's best (it used to lag one evaluation behind)."""
    import itertools
    import re
    counter = itertools.count(1)          # every val evaluation better than the last

    def rising(*_):
        v = next(counter) / 10
        return {"success": v, "spl": v / 2}
    monkeypatch.setattr(loop, "evaluate_on_val", rising)
    capsys.readouterr()
    summary = loop.train(small_cfg(tiny_dir, tmp_path / "run"), progress=True)
    assert summary["best_val"]["success"] > 0.1              # the last eval is the best
    shown = re.findall(r"best_val=([0-9.]+)", capsys.readouterr().err)
    assert shown and shown[-1] == f"{summary['best_val']['success']:.3f}", shown[-3:]


@pytest.mark.parametrize("preset, label", [("baseline", "train baseline"),
                                           ("il", "train baseline+il"),
                                           ("org_il", "train org+il"),
                                           ("dsavn", "train baseline+savn")])
def test_progress_names_the_model_and_what_trains_it(preset, label):
    """Progress lines name the model and IL or SAVN where they train it, so that the IL
    row's lines differ from the Baseline's."""
    assert loop.stage_label(get_config(preset)) == label
