"""Issue 41: the releases' procedure as options. WE / SAVN's target in SAVN's layout with
word vectors read from a GloVe text file (or the stand-in), runs saved before keeping
their one-hot maps; `--optim release`; SAVN's sampled evaluation. (The TPN's placement:
tests/test_tpn_lowrank.py and tests/test_tpn.py.)"""

from __future__ import annotations

import dataclasses
import json
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from orgnav_jax.constants import CATEGORIES
from orgnav_jax.models import build_model
from orgnav_jax.models.navmodel import _init_params, dummy_inputs
from orgnav_jax.models.word_vectors import (
    STAND_IN, camel_words, category_table, category_vectors, label, stand_in)
from orgnav_jax.training.config import get_config, load_config
from orgnav_jax.training.update import make_optimizer

WIDTHS = dict(hidden=8, glob_channels=2, fuse_channels=2, action_embed=3)
D = 5


def glove_file(path, extra=()):
    """A small GloVe text file: the lower-case words of every category, D = 5, and
    `extra` lines; -> {word: vector}."""
    rng = np.random.default_rng(0)
    words = sorted({w for c in CATEGORIES for w in camel_words(c)})
    vectors = {w: rng.standard_normal(D).round(4) for w in words}
    lines = [f"{w} " + " ".join(f"{x:.4f}" for x in v) for w, v in vectors.items()]
    path.write_text("\n".join(["the 0 0 0 0 1", *lines, *extra]) + "\n")
    return vectors


def test_word_vectors_are_read_from_a_glove_file_and_a_malformed_one_is_refused(tmp_path):
    good = tmp_path / "glove.txt"
    vectors = glove_file(good, extra=["coffeemachine 1 2 3 4 5"])
    table = category_vectors(good)
    assert table.shape == (22, D) and table.dtype == np.float32
    i = CATEGORIES.index
    np.testing.assert_allclose(table[i("Television")], vectors["television"], rtol=1e-6)
    # a name the file has whole wins; else the mean of its camel-case words
    np.testing.assert_allclose(table[i("CoffeeMachine")], [1, 2, 3, 4, 5])
    np.testing.assert_allclose(table[i("AlarmClock")],
                               (vectors["alarm"] + vectors["clock"]) / 2, rtol=1e-6)
    assert camel_words("StoveBurner") == ["stove", "burner"] and \
        camel_words("TVStand") == ["tv", "stand"]
    cases = {
        "short.txt": ("the 0 0 0 0 1\nbook 1 2 3\n", "short.txt, line 2: 3 numbers, expected 5"),
        "nan.txt": ("book 1 2 x 4 5\n", "nan.txt, line 1: 'book' has a value that is not a "
                                        "number"),
        "inf.txt": ("book 1 2 inf 4 5\n", "inf.txt, line 1: 'book' has a value that is not a "
                                          "finite"),
        "empty.txt": ("", "empty.txt: empty file"),
        "blank.txt": ("book 1 2\n\nbowl 1 2\n", "blank.txt, line 2: empty line"),
        "lack.txt": ("book 1 2\n", "lack.txt: no vector for 'alarm' (category AlarmClock"),
    }
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError) as err:
            category_vectors(tmp_path / name)
        assert message in str(err.value) and "\n" not in str(err.value), name
    with pytest.raises(FileNotFoundError, match="no such file"):
        category_vectors(tmp_path / "absent.txt")
    # the stand-in: fixed unit vectors, 300-d, labelled as such
    a = stand_in()
    assert a.shape == (22, 300) and np.allclose(np.linalg.norm(a, axis=1), 1)
    np.testing.assert_array_equal(category_table(None).array(), a)
    assert STAND_IN in label(None) and "glove.txt" in label(str(good))


def test_we_is_savns_layout_and_old_we_runs_keep_the_onehot_maps(tmp_path):
    """The target's vector -> Dense 64 -> ReLU, the same 64 values at every cell, fused
    with G + 64 + A channels; another file's vectors change the output. A version-6 WE
    config reads as target_input "onehot_maps" and builds the encoder it was trained with."""
    path = tmp_path / "glove.txt"
    glove_file(path)
    cfg = get_config("we", word_vectors=str(path), **WIDTHS)
    model = build_model(cfg, None)
    inputs = dummy_inputs(22, 4, 4)._replace(target=jax.nn.one_hot(jnp.array([5]), 22))
    params = _init_params(model, jax.random.PRNGKey(0), 22, 4, 4)      # jitted
    enc = params["params"]["encoder"]["embed_glove"]
    assert enc["kernel"].shape == (D, 64)
    assert params["params"]["trunk"]["fuse_1x1"]["kernel"].shape == (2 + 64 + 3, 2)
    maps = jax.jit(lambda p, x: model.apply(p, x.app, x.box, x.conf, x.target,
                                            method=lambda m, *a: m.encoder(*a)))(params, inputs)
    want = jax.nn.relu(category_vectors(path)[5] @ enc["kernel"] + enc["bias"])
    assert maps.shape == (1, 64, 49)
    np.testing.assert_allclose(maps[0], np.repeat(np.asarray(want)[:, None], 49, 1),
                               rtol=1e-5, atol=1e-6)
    stand = build_model(dataclasses.replace(cfg, word_vectors=None), None)
    p2 = jax.eval_shape(lambda: stand.init({"params": jax.random.PRNGKey(0)}, inputs,
                                           stand.initial_carry(1)))
    assert p2["params"]["encoder"]["embed_glove"]["kernel"].shape == (300, 64)
    # a WE run saved before issue 41 (config version 6) keeps its one-hot maps
    doc = json.loads(cfg.to_json())
    for k in ("target_input", "word_vectors", "optim", "savn_act"):
        doc.pop(k)
    (tmp_path / "config.json").write_text(json.dumps({**doc, "version": 6}))
    old = load_config(tmp_path)
    assert (old.target_input, old.word_vectors, old.optim, old.savn_act) == (
        "onehot_maps", None, "ours", "greedy")
    m_old = build_model(old, None)
    p_old = jax.eval_shape(lambda: m_old.init({"params": jax.random.PRNGKey(0)}, inputs,
                                              m_old.initial_carry(1)))
    assert p_old["params"]["encoder"]["target_embedding"]["kernel"].shape == (22, 22 * 49)


def test_a_malformed_word_vector_file_is_one_line_before_any_write(tmp_path, tiny_dir,
                                                                   cli_error):
    from orgnav_jax.train import main
    bad = tmp_path / "bad.txt"
    bad.write_text("book 1 2 3\nbowl 1 2\n")
    run = tmp_path / "run"
    line = cli_error(main, ["--preset", "we", "--scenes-dir", tiny_dir, "--run-dir", run,
                            "--word-vectors", bad, "--quiet"])
    assert "bad.txt, line 2: 2 numbers, expected 3" in line
    assert not run.exists()


def test_optim_release_is_the_releases_settings():
    cfg = get_config("baseline", optim="release")
    assert (cfg.lr, cfg.adam_eps, cfg.max_grad_norm, cfg.gae_lambda, cfg.rollout_len) == (
        1e-4, 1e-3, 100.0, 1.0, 30)
    assert get_config("baseline", optim="release", lr=3e-4).lr == 3e-4    # given: kept
    assert get_config("baseline").optim == "ours" and get_config("baseline").lr == 7e-4
    params = {"w": jnp.ones(3)}
    big = {"w": jnp.array([3e3, 4e3, 0.0])}             # norm 5,000
    for savn, clipped in ((False, True), (True, False)):
        opt = make_optimizer(dataclasses.replace(cfg, savn=savn))
        state = opt.init(params)
        _, state = opt.update(big, state, params)
        amsgrad = [s for s in jax.tree_util.tree_leaves(
            state, is_leaf=lambda s: isinstance(s, optax.ScaleByAmsgradState))
            if isinstance(s, optax.ScaleByAmsgradState)]
        assert len(amsgrad) == 1, savn                    # AMSGrad, not Adam
        norm = float(jnp.linalg.norm(amsgrad[0].mu["w"])) / 0.1   # (1 - b1) x the gradient
        assert np.isclose(norm, 100.0 if clipped else 5000.0, rtol=1e-4), (savn, norm)


def test_savn_act_is_a_checked_option():
    """SAVN's evaluation samples in its release (agents/agent.py:120): savn_act "sample",
    the default (issue 41: the release's, no val comparison needed); greedy is the option."""
    assert get_config("savn").savn_act == get_config("dsavn").savn_act == "sample"
    assert get_config("savn", savn_act="greedy").savn_act == "greedy"
    with pytest.raises(ValueError, match="config field 'savn_act': 'argmax'"):
        get_config("savn", savn_act="argmax")


def test_optim_release_sums_the_loss_over_each_episodes_steps(monkeypatch):
    """`--optim release`: the A2C + IL loss is summed over the steps of the rollout (the
    release's per-episode sum) and averaged over the environments, i.e. T x ours (a mean
    over all T x N steps), computed here term by term from the same logits and values."""
    from orgnav_jax.training import losses
    T, N = 5, 3
    rng = np.random.default_rng(0)
    logits = jnp.asarray(rng.standard_normal((T, N, 6)), jnp.float32)
    values = jnp.asarray(rng.standard_normal((T, N)), jnp.float32)
    monkeypatch.setattr(losses, "replay", lambda *a, **k: (logits, values))
    traj = SimpleNamespace(action=jnp.asarray(rng.integers(0, 6, (T, N))),
                           expert_action=jnp.asarray(rng.integers(0, 6, (T, N))),
                           fresh=jnp.zeros((T, N), bool))
    adv = jnp.asarray(rng.standard_normal((T, N)), jnp.float32)
    ret = jnp.asarray(rng.standard_normal((T, N)), jnp.float32)
    ours = get_config("baseline", il="all")
    release = dataclasses.replace(ours, optim="release")
    loss_ours, _ = losses.a2c_loss(None, None, None, traj, None, adv, ret, ours)
    loss_release, _ = losses.a2c_loss(None, None, None, traj, None, adv, ret, release)
    logp = np.asarray(jax.nn.log_softmax(logits), np.float64)
    p = np.exp(logp)
    pick = lambda a: np.take_along_axis(logp, np.asarray(a)[..., None], -1)[..., 0]
    per_step = (-np.asarray(adv) * pick(traj.action)
                + ours.value_coef * 0.5 * (np.asarray(ret) - np.asarray(values)) ** 2
                + ours.entropy_coef * (p * logp).sum(-1)
                - ours.il_weight * pick(traj.expert_action))        # (T, N)
    assert np.isclose(float(loss_release), per_step.sum(0).mean(), rtol=1e-5)
    assert np.isclose(float(loss_ours), per_step.mean(), rtol=1e-5)


def test_evaluate_savn_act_overrides_a_savn_runs_test_time_actions(monkeypatch, capsys):
    """`evaluate --savn-act sample|greedy` (api.load_policy(savn_act=...)) sets a SAVN
    run's test-time actions; on a run without SAVN, or without a run, it is one line."""
    from orgnav_jax import api
    from orgnav_jax.errors import UserError, run_cli
    from orgnav_jax.evaluate import main
    from orgnav_jax.training import runs, savn
    cfg = {"cfg": get_config("dsavn")}
    monkeypatch.setattr(runs, "load_run_model", lambda run_dir, best=True: (None, {}, cfg["cfg"]))
    monkeypatch.setattr(runs, "scenes_for", lambda c: None)
    seen = []
    monkeypatch.setattr(savn, "run_policy", lambda c, model, scenes: seen.append(c.savn_act)
                        or SimpleNamespace(name=c.savn_act))
    assert api.load_policy(run_dir="r").policy.name == "sample"           # the run's own
    assert api.load_policy(run_dir="r", savn_act="greedy").policy.name == "greedy"
    assert seen == ["sample", "greedy"]
    cfg["cfg"] = get_config("baseline")
    with pytest.raises(UserError, match="--savn-act: r is a baseline run without SAVN"):
        api.load_policy(run_dir="r", savn_act="sample")
    assert run_cli(main, ["--policy", "random", "--savn-act", "sample", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--savn-act needs --checkpoint" in err[0]


# ---- issue 55 (bad input, round four): word vectors ------------------------------------

def test_a_word2vec_header_is_skipped_and_a_word_given_twice_is_refused(tmp_path):
    """word2vec's "N D" first line was "a line with the wrong count of numbers": it is
    skipped when the vectors have D numbers, and named as a header when they do not; a
    word the categories need given twice with other numbers is refused (twice the same
    is accepted)."""
    plain = tmp_path / "plain.txt"
    glove_file(plain)
    lines = plain.read_text().splitlines()
    (tmp_path / "w2v.txt").write_text("\n".join([f"{len(lines)} {D}", *lines]) + "\n")
    np.testing.assert_array_equal(category_vectors(tmp_path / "w2v.txt"),
                                  category_vectors(plain))
    book = next(line for line in lines if line.startswith("book "))
    cases = {
        "header.txt": (f"{len(lines)} 300\n" + "\n".join(lines),
                       f"line 1: '{len(lines)} 300' looks like a word2vec header ('N D'), "
                       f"but line 2 has {D} numbers, not 300"),
        "only.txt": ("400000 300", "only a header line '400000 300'"),
        "twice.txt": ("\n".join([*lines, "book 9 9 9 9 9"]),
                      f"line {len(lines) + 1}: 'book' is given again (first on line "),
        "cut.txt": ("\n".join([lines[0], "book 1 2"]), "line 2: 2 numbers, expected 5 "
                                                       "(line 1's, the first vector's)"),
    }
    for name, (text, message) in cases.items():
        (tmp_path / name).write_text(text + "\n")
        with pytest.raises(ValueError) as err:
            category_vectors(tmp_path / name)
        assert message in str(err.value) and "\n" not in str(err.value), (name, err.value)
    (tmp_path / "same.txt").write_text("\n".join([*lines, book]) + "\n")
    np.testing.assert_array_equal(category_vectors(tmp_path / "same.txt"),
                                  category_vectors(plain))


def test_word_vectors_go_only_with_a_model_that_reads_them(tmp_path, tiny_dir, cli_error):
    """--word-vectors with a model that reads none was kept in the config and silently
    ignored (--pretrained and --tpn-lr are refused there): refused the same way, before
    anything is written; so are an empty path and a malformed sha256."""
    from orgnav_jax.train import main
    path = tmp_path / "glove.txt"
    glove_file(path)
    for preset, extra, message in (
            ("baseline", {}, "model 'baseline' reads no word vectors"),
            ("dsavn", {}, "model 'baseline' reads no word vectors"),
            ("org", {}, "model 'org' reads no word vectors"),
            ("we", {"target_input": "onehot_maps"}, "target_input 'onehot_maps' reads no"),
            ("we", {"word_vectors": " "}, "an empty path")):
        with pytest.raises(ValueError, match="config field 'word_vectors'") as err:
            get_config(preset, **{"word_vectors": str(path), **extra})
        assert message in str(err.value), preset
    for digest in ("abc", "F" * 64):
        with pytest.raises(ValueError, match="'word_vectors_sha256'.*64 lower-case hex"):
            get_config("we", word_vectors=str(path), word_vectors_sha256=digest)
    with pytest.raises(ValueError, match="'word_vectors_sha256'"):
        get_config("we", word_vectors_sha256="0" * 64)
    assert get_config("savn", word_vectors=str(path)).word_vectors == str(path)
    run = tmp_path / "run"
    line = cli_error(main, ["--preset", "dsavn", "--scenes-dir", tiny_dir, "--run-dir", run,
                            "--word-vectors", path, "--quiet"])
    assert "config field 'word_vectors'" in line and "reads no word vectors" in line
    assert not run.exists()


def test_a_run_keeps_the_sha256_of_its_word_vectors_and_refuses_others(tmp_path, tiny_dir,
                                                                        cli_error):
    """A run kept only the file's path: a changed or replaced file gave other vectors
    (other episodes) without a word. A fresh run records the sha256 of the (22, D)
    vectors it reads in its config; evaluation and resume refuse a file whose vectors
    are others (before any checkpoint is read or anything written); the same vectors in
    another layout are accepted."""
    from orgnav_jax import evaluate, train
    from orgnav_jax.models.word_vectors import category_table
    from orgnav_jax.training.runs import keep_word_vectors, load_run_model
    path = tmp_path / "glove.txt"
    glove_file(path)
    run = tmp_path / "run"
    run.mkdir()
    fresh = get_config("we", word_vectors=str(path), scenes_dir=tiny_dir, run_dir=str(run),
                       **WIDTHS)
    assert fresh.word_vectors_sha256 is None
    kept = keep_word_vectors(fresh)
    assert kept.word_vectors_sha256 == category_table(str(path)).sha256
    (run / "config.json").write_text(kept.to_json())     # what the run's config holds
    assert load_config(run).word_vectors_sha256 == kept.word_vectors_sha256
    # the same vectors, reordered lines and other spacing: the same sha256
    lines = path.read_text().splitlines()
    path.write_text("\n".join(["  ".join(line.split()) for line in reversed(lines)]) + "\n")
    assert keep_word_vectors(fresh, resume=True) == kept
    path.write_text("\n".join("book 1 2 3 4 5" if line.startswith("book ") else line
                              for line in lines) + "\n")     # 'book' is now another vector
    before = sorted(p.name for p in run.iterdir())
    message = f"word vectors {path}: not the vectors of the run {run}"
    with pytest.raises(ValueError, match="not the vectors of the run") as err:
        load_run_model(run)                  # before any checkpoint (there is none)
    assert message in str(err.value)
    with pytest.raises(ValueError, match="not the vectors of the run"):
        keep_word_vectors(fresh, resume=True)           # the options given again
    assert message in cli_error(evaluate.main, ["--checkpoint", run, "--quiet"])
    assert message in cli_error(train.main, ["--run-dir", run, "--resume", "--quiet"])
    assert sorted(p.name for p in run.iterdir()) == before


def test_the_same_word_vectors_at_a_new_path_resume_the_run(tmp_path, tiny_dir, cli_error):
    """Issue 67: a run whose word-vector file was moved was refused on resume with the
    file's new path (`--word-vectors` was no resume option, and the path was compared as
    a field) although its vectors (their sha256) were the run's. The new path is taken,
    like a moved --scenes-dir, where the run keeps the sha256; other vectors there are
    refused; a run that keeps no sha256 (older) still compares the path."""
    from orgnav_jax import train
    from orgnav_jax.training.run_dir import check_run_dir
    from orgnav_jax.training.runs import keep_word_vectors
    old, new = tmp_path / "glove.txt", tmp_path / "moved" / "glove.txt"
    glove_file(old)
    run = tmp_path / "run"
    run.mkdir()
    kept = keep_word_vectors(get_config("we", word_vectors=str(old), scenes_dir=tiny_dir,
                                        run_dir=str(run), **WIDTHS))
    (run / "config.json").write_text(kept.to_json())
    new.parent.mkdir()
    old.rename(new)
    cfg = train.nav_config(train.parser().parse_args(
        ["--run-dir", str(run), "--resume", "--word-vectors", str(new)]))
    assert cfg.word_vectors == str(new)
    cfg = keep_word_vectors(cfg, resume=True)
    assert cfg.word_vectors_sha256 == kept.word_vectors_sha256
    check_run_dir(run, cfg, True, load_config)          # the same run: no difference
    lines = new.read_text().splitlines()
    new.write_text("\n".join("book 1 2 3 4 5" if line.startswith("book ") else line
                             for line in lines) + "\n")
    before = sorted(p.name for p in run.iterdir())
    assert f"word vectors {new}: not the vectors of the run {run}" in cli_error(
        train.main, ["--run-dir", run, "--resume", "--word-vectors", new, "--quiet"])
    assert sorted(p.name for p in run.iterdir()) == before
    unkept = dataclasses.replace(kept, word_vectors_sha256=None)
    (run / "config.json").write_text(unkept.to_json())
    with pytest.raises(ValueError, match=r"differs from the requested config \(word_vectors: "):
        check_run_dir(run, dataclasses.replace(cfg, word_vectors_sha256=None), True,
                      load_config)
