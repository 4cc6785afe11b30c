"""Bad configs and evaluation inputs (issue 13, items 7-8): every one is a one-line error
with exit code 2 before anything is written or compiled, and nothing pre-existing
changes. Plain unit tests of the config ranges, the memory estimate and the budget
notice come first."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from orgnav_jax import episodes as E
from orgnav_jax import evaluate, evaluation
from orgnav_jax import scenes as scenes_mod
from orgnav_jax import train as train_cli
from orgnav_jax.constants import split_index
from orgnav_jax.tpn.config import TPNConfig, get_tpn_config
from orgnav_jax.training import memory
from orgnav_jax.training.config import TrainConfig, get_config

NAN, INF = float("nan"), float("inf")


# ------------------------------------------------------------------ config ranges

@pytest.mark.parametrize("field, value, message", [
    ("eval_every_chunks", 0, "'eval_every_chunks': 0, expected an integer eval_every_chunks >= 1"),
    ("checkpoint_every_chunks", 0, "expected an integer checkpoint_every_chunks >= 1"),
    ("eval_episodes_per_room_type", 0, "eval_episodes_per_room_type >= 1"),
    ("glob_channels", 0, "'glob_channels': 0, expected an integer glob_channels >= 1"),
    ("action_embed", 0, "action_embed >= 1"),
    ("fuse_channels", -3, "fuse_channels >= 1"),
    ("hidden", 0, "hidden >= 1"),
    ("lstm_layers", 0, "lstm_layers >= 1"),
    ("num_envs", 0, "num_envs >= 1"),
    ("rollout_len", 0, "rollout_len >= 1"),
    ("total_env_steps", 0, "total_env_steps >= 1"),
    ("updates_per_chunk", 0, "updates_per_chunk >= 1"),
    ("keep_checkpoints", 0, "'keep_checkpoints': 0, expected an integer keep_checkpoints >= 1"),
    ("episode_cap", 0, "1 <= episode_cap <= 2,147,483,646"),
    ("episode_cap", 2 ** 31, "1 <= episode_cap <= 2,147,483,646"),
    ("seed", -1, "'seed': -1, expected an integer 0 <= seed"),
    ("scene_seed", -1, "0 <= scene_seed"),
    ("lr", NAN, "'lr': nan, expected lr > 0, finite"),
    ("lr", -1.0, "'lr': -1.0, expected lr > 0, finite"),
    ("lr", 0.0, "expected lr > 0"),
    ("lr", INF, "'lr': inf"),
    ("adam_eps", 0.0, "adam_eps > 0"),
    ("max_grad_norm", -1.0, "max_grad_norm > 0"),
    ("gamma", 2.0, "config field 'gamma': 2.0, expected 0 < gamma <= 1"),
    ("gamma", 0.0, "0 < gamma <= 1"),
    ("gamma", NAN, "0 < gamma <= 1"),
    ("gae_lambda", 1.5, "0 <= gae_lambda <= 1"),
    ("gae_lambda", -0.1, "0 <= gae_lambda <= 1"),
    ("entropy_coef", -0.01, "entropy_coef >= 0, finite"),
    ("value_coef", NAN, "value_coef >= 0, finite"),
    ("il_weight", -1.0, "il_weight >= 0, finite"),
    ("success_reward", INF, "a finite success_reward"),
    ("step_penalty", NAN, "a finite step_penalty"),
    ("dropout", 1.0, "'dropout' must lie in [0, 1)"),
    ("num_envs", 2.5, "'num_envs': 2.5, expected an integer"),
    ("hidden", True, "'hidden': True, expected an integer"),
    ("lr", "fast", "'lr': 'fast', expected a number"),
    ("run_dir", None, "'run_dir': None, expected a string"),
])
def test_train_config_ranges(field, value, message):
    with pytest.raises(ValueError, match="config field") as err:
        get_config("small", **{field: value})
    assert message in str(err.value)
    assert field in str(err.value)


@pytest.mark.parametrize("fields", [
    dict(gamma=1.0, gae_lambda=0.0), dict(gae_lambda=1.0), dict(entropy_coef=0.0,
    value_coef=0.0, il_weight=0.0), dict(step_penalty=0.0, success_reward=-1.0),
    dict(seed=0, scene_seed=0), dict(episode_cap=1, keep_checkpoints=1), dict(lr=1, gamma=1),
])
def test_train_config_edges_are_valid(fields):
    get_config("small", **fields)


@pytest.mark.parametrize("field, value, message", [
    ("action_embed", 0, "action_embed >= 1"), ("top_k", 0, "top_k >= 1"),
    ("signature_dim", 0, "signature_dim >= 1"),
    ("episode_cap", 0, "1 <= episode_cap"), ("num_envs", 0, "num_envs >= 1"),
    ("total_episodes", 0, "total_episodes >= 1"),
    ("updates_per_chunk", 0, "updates_per_chunk >= 1"),
    ("eval_every_chunks", 0, "'eval_every_chunks': 0, expected an integer "
                             "eval_every_chunks >= 1"),
    ("eval_episodes_per_room_type", 0, "eval_episodes_per_room_type >= 1"),
    ("checkpoint_every_chunks", 0, "checkpoint_every_chunks >= 1"),
    ("keep_checkpoints", 0, "keep_checkpoints >= 1"),
    ("seed", -1, "0 <= seed"),
    ("lr", NAN, "'lr': nan, expected lr > 0, finite"), ("lr", 0.0, "lr > 0"),
    ("max_grad_norm", -1.0, "max_grad_norm > 0"),
    ("tpn_lr", -1e-3, "tpn_lr >= 0, finite (0: no test-time update)"),
    ("tpn_lr", INF, "tpn_lr >= 0"),
    ("reset_every", -1, "reset_every >= 0 (0: reset at episode starts only)"),
    ("cosine_threshold", 1.5, "-1 <= cosine_threshold <= 1"),
    ("cosine_threshold", NAN, "-1 <= cosine_threshold <= 1"),
    ("scope", "everything", "'scope': 'everything', expected one of"),
    ("tpn_train_mode", 1, "'tpn_train_mode': 1, expected true or false"),
])
def test_tpn_config_ranges(field, value, message):
    with pytest.raises(ValueError, match="TPN config field") as err:
        get_tpn_config(**{field: value})
    assert message in str(err.value)


def test_tpn_config_edges_are_valid():
    """tpn_lr 0 (the base alone), reset_every 0 (reset at episode starts only) and the
    cosine threshold's ends are meaningful."""
    get_tpn_config(tpn_lr=0.0, reset_every=0, cosine_threshold=-1.0)
    get_tpn_config(cosine_threshold=1.0, episode_cap=1, top_k=1)


def test_every_numeric_field_has_a_range():
    from orgnav_jax.tpn.config import FIELD_RANGES as TPN_RANGES
    from orgnav_jax.training.config import FIELD_RANGES
    for cls, ranges, checked_apart in ((TrainConfig, FIELD_RANGES, {"dropout"}),
                                       (TPNConfig, TPN_RANGES, set())):
        numeric = {f.name for f in dataclasses.fields(cls)
                   if type(f.default) in (int, float)}
        assert numeric - checked_apart == set(ranges), cls


# ------------------------------------------------------------------ budget rounding

@pytest.mark.parametrize("version", [2, 3, 4])
def test_configs_before_version_5_read_max_steps_as_episode_cap(tmp_path, version):
    from orgnav_jax.tpn.config import load_tpn_config
    from orgnav_jax.training.config import CONFIG_VERSION, load_config
    for stage, cfg, load in (("nav", get_config("tiny", episode_cap=17), load_config),
                             ("tpn", get_tpn_config(episode_cap=23), load_tpn_config)):
        doc = dataclasses.asdict(cfg)
        doc["max_steps"] = doc.pop("episode_cap")
        run = tmp_path / stage
        run.mkdir()
        (run / "config.json").write_text(json.dumps({"version": version, "stage": stage,
                                                     **doc}))
        assert load(run).episode_cap == cfg.episode_cap
        assert json.loads(cfg.to_json())["version"] == CONFIG_VERSION == 9
        assert "max_steps" not in json.loads(cfg.to_json())
        doc["version"] = 5               # a version-5 config with the old name is refused
        (run / "config.json").write_text(json.dumps({"stage": stage, **doc}))
        with pytest.raises(ValueError, match=r"unknown config field\(s\) \['max_steps'\]"):
            load(run)


def test_a_stage2_run_of_the_tpn_head_before_the_releases_is_refused(tmp_path):
    """A TPN config saved before issue 39 (its 'mlp' field: another network, whose
    parameters this TPN cannot read) is a one-line error naming the file; a current one
    reads back with the release's widths."""
    from orgnav_jax.tpn.config import load_tpn_config
    doc = json.loads(get_tpn_config(episode_cap=23).to_json())
    (tmp_path / "config.json").write_text(json.dumps(doc))
    cfg = load_tpn_config(tmp_path)
    assert (cfg.action_embed, cfg.top_k, cfg.episode_cap) == (6, 10, 23)
    (tmp_path / "config.json").write_text(json.dumps({**doc, "action_embed": 32, "mlp": 256}))
    with pytest.raises(ValueError, match="TPN head before the release's") as err:
        load_tpn_config(tmp_path)
    line = str(err.value)
    assert line.startswith(str(tmp_path / "config.json")) and "\n" not in line


def test_max_steps_is_the_old_name_of_the_episode_cap_flag():
    from orgnav_jax.training.config import overrides_from_args
    args = train_cli.parser().parse_args(["--max-steps", "12"])
    assert overrides_from_args(args)["episode_cap"] == 12


def test_budget_notice_names_the_steps_run():
    cfg = get_config("tiny", total_env_steps=10)
    assert cfg.budget_notice() == ("note: total_env_steps 10 rounds up to 10,240 (whole "
                                   "chunks of 10 updates x 64 envs x 16 steps)")
    exact = get_config("tiny", total_env_steps=64 * 16 * 10 * 3)
    assert exact.budget_notice() is None
    down = get_config("tiny", total_env_steps=1500, updates_per_chunk=1)
    assert "rounds down to 1,024 (whole chunks of 1 update x" in down.budget_notice()
    tpn = get_tpn_config(total_episodes=10)
    assert tpn.budget_notice() == ("note: total_episodes 10 rounds up to 640 (whole chunks "
                                   "of 10 updates x 64 episodes)")
    assert get_tpn_config(total_episodes=6400).budget_notice() is None


# ------------------------------------------------------------------ fixtures

@pytest.fixture(scope="module")
def no_val_dir(tmp_path_factory, tiny_scenes):
    """The tiny scenes with their val rooms relabelled as train rooms."""
    split = np.asarray(tiny_scenes.split)
    split = np.where(split == split_index("val"), split_index("train"), split)
    path = tmp_path_factory.mktemp("scenes") / "noval"
    scenes_mod.save(tiny_scenes.replace(split=split.astype(np.int32)), path)
    return str(path)


@pytest.fixture(scope="module")
def base_run(tmp_path_factory, tiny_dir):
    """A training run directory with only its config.json (enough for TPN config errors
    and the stage-2 memory check, which come before the base model is loaded)."""
    path = tmp_path_factory.mktemp("base") / "base"
    path.mkdir()
    cfg = get_config("tiny", scenes_dir=tiny_dir, run_dir=str(path))
    (path / "config.json").write_text(cfg.to_json())
    return path


def snapshot(root):
    """{relative path: bytes} of every file under root."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


# ------------------------------------------------------------------ memory estimate

def test_memory_estimate_passes_the_default_and_fails_episode_cap_1e9(tiny_scenes):
    small = get_config("small")
    parts = memory.chunk_memory_bytes(small, tiny_scenes)
    assert 50e6 < sum(parts.values()) < 2e9, parts
    memory.check_memory(small, tiny_scenes)             # fits on any machine that tests
    huge = get_config("small", episode_cap=1_000_000_000)
    assert memory.chunk_memory_bytes(huge, tiny_scenes)["trail"] > 256e9
    with pytest.raises(ValueError, match=r"training needs ~768 GB of memory per chunk "
                                         r"\(episode_cap 1000000000 x num_envs 64: ~768 GB\)"):
        memory.check_memory(huge, tiny_scenes)


def test_memory_check_notes_a_near_miss_and_fails_beyond_twice(tiny_scenes, capsys):
    cfg = get_config("small")
    need = sum(memory.chunk_memory_bytes(cfg, tiny_scenes).values())
    assert memory.check_memory(cfg, tiny_scenes, available=2 * need) == need
    assert capsys.readouterr().err == ""
    memory.check_memory(cfg, tiny_scenes, available=need * 2 // 3, where="test memory")
    assert "it may not fit" in capsys.readouterr().err
    with pytest.raises(ValueError, match="this machine has .* test memory: lower those "
                                         "fields"):
        memory.check_memory(cfg, tiny_scenes, available=need // 3, where="test memory")


def test_tpn_memory_grows_with_episode_cap_squared(tiny_scenes):
    nav = get_config("small")
    short = memory.tpn_memory_bytes(get_tpn_config(episode_cap=1000), nav, tiny_scenes)
    long = memory.tpn_memory_bytes(get_tpn_config(episode_cap=2000), nav, tiny_scenes)
    assert long["attention"] == 4 * short["attention"]
    memory.check_tpn_memory(get_tpn_config(), nav, tiny_scenes)
    with pytest.raises(ValueError, match=r"TPN stage 2 needs .*episode_cap 100000\^2"):
        memory.check_tpn_memory(get_tpn_config(episode_cap=100_000), nav, tiny_scenes)


# ------------------------------------------------------------------ train CLI

TRAIN_CASES = [
    (["--eval-every-chunks", "0"], "config field 'eval_every_chunks': 0, expected an "
                                   "integer eval_every_chunks >= 1"),
    (["--checkpoint-every-chunks", "0"], "'checkpoint_every_chunks': 0"),
    (["--eval-episodes-per-room-type", "0"], "'eval_episodes_per_room_type': 0"),
    (["--glob-channels", "0"], "'glob_channels': 0, expected an integer glob_channels >= 1"),
    (["--lr", "nan"], "config field 'lr': nan, expected lr > 0, finite"),
    (["--lr", "-1"], "config field 'lr': -1.0, expected lr > 0, finite"),
    (["--gamma", "2"], "config field 'gamma': 2.0, expected 0 < gamma <= 1"),
    (["--keep-checkpoints", "0"], "'keep_checkpoints': 0"),
    (["--episode-cap", "1000000000"], "training needs ~768 GB of memory per chunk (episode_cap "
                                    "1000000000 x num_envs 64: ~768 GB); this machine has"),
    # issue 38: SAVN segments that leave no inner step, and inner-step slots (87 TB) that
    # reached XLA after the run directory was written
    (["--preset", "dsavn", "--savn-steps", "31"], "config field 'savn_steps': 31, expected < "
     "episode_cap 30 with savn: segments of 31 steps leave no inner step"),
    (["--preset", "dsavn", "--savn-steps", "1000000", "--savn-inner-steps", "2000"],
     "config field 'savn_steps': 1000000, expected < episode_cap 30"),
    (["--preset", "dsavn", "--savn-steps", "29", "--savn-inner-steps", "1000000"],
     "(num_envs 64 x savn_inner_steps 1000000 x savn_steps 29: ~"),
]


@pytest.mark.parametrize("argv, message", TRAIN_CASES)
def test_train_cli_rejects_bad_configs_before_writing(tmp_path, tiny_dir, cli_error, argv,
                                                      message):
    run_dir = tmp_path / "run"
    line = cli_error(train_cli.main, ["--preset", "tiny", "--scenes-dir", tiny_dir,
                                      "--run-dir", run_dir, "--quiet", *argv])
    assert message in line
    assert not run_dir.exists()                  # no config.json, nothing compiled


def test_train_cli_leaves_an_existing_run_dir_untouched(tmp_path, tiny_dir, cli_error):
    run_dir = tmp_path / "run"
    (run_dir / "notes").mkdir(parents=True)
    (run_dir / "thesis.txt").write_text("years of work")
    (run_dir / "notes" / "a.md").write_text("more")
    before = snapshot(run_dir)
    for argv, message in TRAIN_CASES[:: 4]:
        assert message in cli_error(train_cli.main, [
            "--preset", "tiny", "--scenes-dir", tiny_dir, "--run-dir", run_dir, *argv])
    assert snapshot(run_dir) == before


def test_train_cli_needs_val_rooms(tmp_path, no_val_dir, cli_error):
    run_dir = tmp_path / "run"
    line = cli_error(train_cli.main, ["--preset", "tiny", "--scenes-dir", no_val_dir,
                                      "--run-dir", run_dir])
    assert line == (f"error: scenes {no_val_dir} have no val rooms (split field): training "
                    "needs val rooms to select the best checkpoint")
    assert not run_dir.exists()


def test_train_cli_prints_the_budget_notice(tmp_path, tiny_dir, monkeypatch, capsys):
    from orgnav_jax.training import loop
    seen = {}

    def fake_train(cfg, **kw):
        seen["cfg"] = cfg
        return {"runner": None}

    monkeypatch.setattr(loop, "train", fake_train)
    train_cli.main(["--preset", "tiny", "--scenes-dir", tiny_dir, "--run-dir",
                    str(tmp_path / "run"), "--total-env-steps", "10", "--no-test", "--quiet"])
    err = capsys.readouterr().err
    assert ("note: total_env_steps 10 rounds up to 10,240 (whole chunks of 10 updates x 64 "
            "envs x 16 steps)") in err
    assert seen["cfg"].total_env_steps == 10        # the loop rounds; the config keeps it


def test_tpn_cli_rejects_bad_configs_before_writing(tmp_path, base_run, cli_error):
    run_dir = tmp_path / "tpn"
    before = snapshot(base_run)
    for argv, message in ((["--eval-every-chunks", "0"], "TPN config field "
                           "'eval_every_chunks': 0, expected an integer eval_every_chunks >= 1"),
                          (["--lr", "nan"], "TPN config field 'lr': nan"),
                          (["--tpn-lr", "-1"], "'tpn_lr': -1.0, expected tpn_lr >= 0"),
                          (["--keep-checkpoints", "0"], "'keep_checkpoints': 0"),
                          (["--episode-cap", "100000"], "TPN stage 2 needs ~")):
        line = cli_error(train_cli.main, ["--stage", "tpn", "--base", base_run,
                                          "--run-dir", run_dir, *argv])
        assert message in line, line
        assert not run_dir.exists()
    assert snapshot(base_run) == before


def test_a_savn_run_is_no_tpn_base_and_resume_does_not_ignore_preset(tmp_path, tiny_dir,
                                                                     cli_error):
    """Issue 38: `--stage tpn --base` a SAVN run is one line before any write (it ended in
    a flax scope error); `--preset P --resume` of a run P does not describe is refused
    (it was ignored without a word); a preset that agrees is accepted."""
    savn = tmp_path / "dsavn"
    savn.mkdir()
    (savn / "config.json").write_text(get_config("dsavn", scenes_dir=tiny_dir,
                                                 run_dir=str(savn)).to_json())
    before = snapshot(savn)
    line = cli_error(train_cli.main, ["--stage", "tpn", "--base", savn,
                                      "--run-dir", tmp_path / "tpn"])
    assert f"--base {savn}: a SAVN run cannot be a TPN base" in line, line
    line = cli_error(train_cli.main, ["--preset", "baseline", "--run-dir", savn, "--resume"])
    assert f"--preset baseline: {savn} was trained with savn True" in line, line
    assert "drop --preset" in line
    assert not (tmp_path / "tpn").exists() and snapshot(savn) == before
    args = train_cli.parser().parse_args(["--preset", "dsavn", "--run-dir", str(savn),
                                          "--resume"])
    assert train_cli.nav_config(args).savn                  # agrees: the saved config


def test_tpn_cli_prints_the_budget_notice(tmp_path, base_run, monkeypatch, capsys):
    from orgnav_jax.tpn import stage2
    monkeypatch.setattr(stage2, "train_tpn", lambda cfg, **kw: {"runner": None})
    train_cli.main(["--stage", "tpn", "--base", str(base_run), "--run-dir",
                    str(tmp_path / "tpn"), "--total-episodes", "10", "--no-test", "--quiet"])
    assert ("note: total_episodes 10 rounds up to 640 (whole chunks of 10 updates x 64 "
            "episodes)") in capsys.readouterr().err


# ------------------------------------------------------------------ evaluate CLI

def expert_argv(tiny_dir, out, *more):
    return ["--policy", "expert", "--split", "val", "--scenes", tiny_dir, "--out", out,
            "--quiet", *more]


@pytest.mark.parametrize("argv, message", [
    (["--episodes-per-room-type", "0"], "error: --episodes-per-room-type 0: expected an "
                                        "integer >= 1"),
    (["--batch-size", "0"], "error: --batch-size 0: expected an integer >= 1"),
    (["--episode-seed", "-1"], "error: --episode-seed -1: expected an integer >= 0"),
])
def test_evaluate_rejects_bad_options(tmp_path, tiny_dir, cli_error, argv, message):
    out = tmp_path / "res.json"
    assert cli_error(evaluate.main, expert_argv(tiny_dir, out, *argv)) == message
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("content", ["[]", '{"format": "orgnav_jax.episodes/1", "split": '
                                           '"val", "seed": 0, "episodes": []}'])
def test_evaluate_rejects_an_empty_episode_file(tmp_path, tiny_dir, cli_error, content):
    episodes = tmp_path / "empty.json"
    episodes.write_text(content)
    out = tmp_path / "res.json"
    line = cli_error(evaluate.main, expert_argv(tiny_dir, out, "--episodes", episodes))
    assert line == f"error: episode file {episodes} holds no episodes: nothing to evaluate"
    assert not out.exists()


@pytest.mark.parametrize("content", [b"my thesis", b'{"a": 1}', b"\x80\x04\x95binary",
                                     b'{"overall": 1}'])
def test_evaluate_out_does_not_overwrite_other_files(tmp_path, tiny_dir, cli_error, content):
    out = tmp_path / "thesis.json"
    out.write_bytes(content)
    line = cli_error(evaluate.main, expert_argv(tiny_dir, out))
    assert line == (f"error: --out {out} exists and is not an evaluation results JSON of "
                    "orgnav_jax.evaluate; it is left untouched: choose another path")
    assert out.read_bytes() == content
    assert [p.name for p in tmp_path.iterdir()] == ["thesis.json"]


def test_evaluate_out_is_not_a_directory(tmp_path, tiny_dir, cli_error):
    line = cli_error(evaluate.main, expert_argv(tiny_dir, tmp_path))
    assert "is a directory, expected a file path" in line


def test_evaluate_does_not_overwrite_a_foreign_file_at_the_episode_path(tmp_path, tiny_dir,
                                                                       cli_error):
    out = tmp_path / "res.json"
    beside = tmp_path / "episodes-tiny-val-seed0.json"
    beside.write_text("not episodes")
    line = cli_error(evaluate.main, expert_argv(tiny_dir, out))
    assert line == (f"error: the episode file beside --out {beside} exists and is not an "
                    "episode file of orgnav_jax.evaluate; it is left untouched: choose "
                    "another path")
    assert beside.read_text() == "not episodes" and not out.exists()


def test_own_outputs_are_recognised(tmp_path, tiny_scenes):
    """Results JSON and episode files of a previous evaluation may be replaced."""
    val = tiny_scenes.split_view("val")
    episodes = E.sample_episodes(val, 2, seed=0, split="val")
    path = tmp_path / "episodes.json"
    E.save_episodes(path, episodes, val)
    assert E.is_episode_file(path) and not evaluate.is_results_json(path)
    res = tmp_path / "res.json"
    res.write_text(json.dumps({"overall": {}, "per_room_type": {}, "per_target": {}},
                              indent=1))
    assert evaluate.is_results_json(res) and not E.is_episode_file(res)
    for bad in (b"", b"[1, 2]", b"\x80\x04binary", b"{" * 100_000):
        (tmp_path / "bad").write_bytes(bad)
        assert not evaluate.is_results_json(tmp_path / "bad")
        assert not E.is_episode_file(tmp_path / "bad")
    assert not E.is_episode_file(tmp_path / "missing")


# ------------------------------------------------------------------ library guards

def test_sampling_and_evaluating_empty_sets_are_clear_errors(tiny_scenes):
    val = tiny_scenes.split_view("val")
    with pytest.raises(ValueError, match="episodes per room type: 0, expected an integer"):
        E.sample_episodes(val, 0)
    # a room type whose targets are never reachable would make sampling loop forever
    targets = np.asarray(val.targets).copy()
    targets[np.asarray(val.room_type) == 0] = False
    with pytest.raises(ValueError, match="no episode can be sampled for the kitchen rooms "
                                         "of split val"):
        E.sample_episodes(val.replace(targets=targets), 2, split="val")
    empty = E.sample_episodes(val, 1).subset(np.zeros(0, int))
    with pytest.raises(ValueError, match="no episodes to evaluate"):
        evaluation.evaluate(evaluation.random_policy(), None, val, empty)


# ------------------------------------------------------------------ config.json (issue 22)

# (field, JSON text of the value, expected message part): what a hand-edited or damaged
# config.json may hold; every one a one-line error naming the file and the field
CONFIG_JSON_CASES = [
    ("lr", "1e400", "config field 'lr': inf, expected lr > 0, finite"),
    ("lr", "1" + "0" * 400, "config field 'lr': an integer of 401 digits, expected a finite"),
    ("num_envs", '"3"', "config field 'num_envs': '3', expected an integer"),
    ("num_envs", "null", "config field 'num_envs': None, expected an integer"),
    ("hidden", "true", "config field 'hidden': True, expected an integer"),
    ("num_envs", str(2 ** 40), "config field 'num_envs': 1099511627776, expected an integer "
                               "num_envs >= 1 and at most 2,147,483,647 (int32)"),
    ("total_env_steps", str(2 ** 40), "'total_env_steps': 1099511627776, expected an integer "
                                      "total_env_steps >= 1 and at most 1,000,000,000,000"),
    ("model", '{"name": "org"}', "config field 'model': {'name': 'org'}, expected a string"),
    ("scenes_dir", "[]", "config field 'scenes_dir': [], expected a string or null"),
    ("version", "5.0", "config version 5.0, this orgnav_jax reads versions [2, 3, 4, 5, 6, 7, 8, 9]"),
    ("stage", '["nav"]', "field 'stage': expected one of ['nav', 'tpn', 'pretrain'], got ['nav']"),
]


def write_config_json(run: Path, cfg, field: str, value: str) -> Path:
    """cfg's config.json in `run` with `field` replaced by the JSON text `value`."""
    run.mkdir(parents=True, exist_ok=True)
    doc = json.loads(cfg.to_json())
    doc[field] = "@VALUE@"
    (run / "config.json").write_text(json.dumps(doc).replace('"@VALUE@"', value))
    return run / "config.json"


@pytest.mark.parametrize("field, value, message", CONFIG_JSON_CASES)
def test_a_malformed_config_json_is_one_line_naming_file_and_field(tmp_path, base_run, field,
                                                                   value, message, cli_error):
    from orgnav_jax.training.config import load_config
    path = write_config_json(tmp_path / "run", get_config("tiny"), field, value)
    with pytest.raises(ValueError) as err:
        load_config(path.parent)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value)
    # --resume reads it first: exit 2, nothing written
    before = snapshot(tmp_path)
    line = cli_error(train_cli.main, ["--run-dir", path.parent, "--resume", "--quiet",
                                      "--no-test"])
    assert line == f"error: {err.value}"
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("field, value, message", [
    ("tpn_lr", "1e400", "TPN config field 'tpn_lr': inf, expected tpn_lr >= 0"),
    ("top_k", '"8"', "TPN config field 'top_k': '8', expected an integer"),
    ("top_k", str(2 ** 40), "'top_k': 1099511627776, expected an integer top_k >= 1 and at "
                            "most 2,147,483,647 (int32)"),
    ("tpn_train_mode", "null", "'tpn_train_mode': None, expected true or false"),
])
def test_a_malformed_tpn_config_json_names_file_and_field(tmp_path, field, value, message):
    from orgnav_jax.tpn.config import load_tpn_config
    path = write_config_json(tmp_path / "tpn", get_tpn_config(), field, value)
    with pytest.raises(ValueError) as err:
        load_tpn_config(path.parent)
    assert str(err.value).startswith(f"{path}: ") and message in str(err.value)


def test_vtnet_resume_of_a_missing_run_dir_is_refused(tmp_path, tiny_dir, cli_error):
    """Issue 55: `--preset vtnet --resume --run-dir MISSING` (a typo) started a fresh
    pre-training and training, where every other preset refuses "holds no run"; with
    seeds too. A pipeline whose pre-training exists still resumes (not tested here:
    it trains)."""
    missing = tmp_path / "vtnte"
    for extra in ([], ["--seeds", "0", "1"]):
        line = cli_error(train_cli.main, ["--preset", "vtnet", "--resume", "--run-dir", missing,
                                          "--scenes-dir", tiny_dir, "--quiet", *extra])
        first, pre = ((f"{missing}-s0", f"{missing}-pretrain-s0") if extra
                      else (missing, f"{missing}-pretrain"))
        assert f"--resume: {first} holds no run, nor {pre} a pre-training" in line, line
    assert sorted(tmp_path.iterdir()) == []
