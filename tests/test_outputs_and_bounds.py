"""Issue 22: pictures and results never replace a file the program did not write, no
option loses its 0 / empty value to a truthiness test, and bounds are checked before
any work (episode counts, both stages' options, the coordinator address)."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import pytest

from orgnav_jax import evaluate as evaluate_cli
from orgnav_jax import plots
from orgnav_jax import train as train_cli
from orgnav_jax.scenes.synthetic.presets import SCENE_PRESETS


def sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


@pytest.fixture()
def curve_run(tmp_path) -> Path:
    """A run directory with val records only (all `plots curves` reads)."""
    run = tmp_path / "baseline-s0"
    run.mkdir()
    lines = [{"kind": "val", "env_steps": s, "success": v, "spl": v / 2}
             for s, v in ((1000, 0.1), (2000, 0.3))]
    (run / "metrics.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    return run


# ------------------------------------------------------------------ pictures

def test_pictures_never_replace_a_users_file(curve_run, tmp_path, cli_error, capsys):
    thesis = tmp_path / "thesis_figure.png"
    thesis.write_bytes(b"\x89PNG\r\n\x1a\n a picture the user made")
    before = sha(thesis)
    msg = cli_error(plots.main, ["curves", curve_run, "--out", thesis])
    assert f"--out {thesis} exists and is not a PNG written by orgnav_jax" in msg
    assert sha(thesis) == before
    # the default output (RUN_DIR/curves.png) when the user has a file there
    mine = curve_run / "curves.png"
    mine.write_text("my notes")
    msg = cli_error(plots.main, ["curves", curve_run])
    assert "curves.png exists and is not a PNG written by orgnav_jax" in msg
    assert mine.read_text() == "my notes"
    mine.unlink()
    # another format than PNG, an empty path, a symbolic link (dangling or not)
    report = tmp_path / "report.pdf"
    report.write_text("%PDF the user's report")
    assert "expected a .png path" in cli_error(plots.main, ["curves", curve_run, "--out",
                                                             report])
    assert report.read_text() == "%PDF the user's report"
    assert "--out is empty" in cli_error(plots.main, ["curves", curve_run, "--out", ""])
    for target in (tmp_path / "nowhere.png", thesis):
        link = tmp_path / f"link-{target.stem}.png"
        link.symlink_to(target)
        assert "is a symbolic link" in cli_error(plots.main, ["curves", curve_run, "--out",
                                                               link])
        assert link.is_symlink() and os.readlink(link) == str(target)
    assert sha(thesis) == before and not (tmp_path / "nowhere.png").exists()


def test_own_pictures_are_marked_replaced_and_printed(curve_run, capsys):
    from orgnav_jax.safe_write import is_own_png
    assert plots.main(["curves", str(curve_run)]) == 0
    out = curve_run / "curves.png"
    assert f"wrote {out}" in capsys.readouterr().out
    assert is_own_png(out)
    first = out.stat().st_mtime_ns
    assert plots.main(["curves", str(curve_run)]) == 0           # ours: replaced
    assert out.stat().st_mtime_ns >= first and is_own_png(out)
    assert not [p for p in curve_run.iterdir() if p.name.endswith(".tmp.png")]


# ------------------------------------------------------------------ evaluate --out

def test_evaluate_out_never_lands_on_a_link_or_an_input(tmp_path, tiny_dir, cli_error):
    base = ["--policy", "random", "--scenes", tiny_dir, "--split", "val",
            "--episodes-per-room-type", "2", "--quiet"]
    link = tmp_path / "results.json"
    link.symlink_to(tmp_path / "missing.json")
    assert "is a symbolic link" in cli_error(evaluate_cli.main, base + ["--out", link])
    assert link.is_symlink() and not (tmp_path / "missing.json").exists()
    # a sampled set is saved beside --out under its own name: --out may not be that name
    clash = tmp_path / "episodes-tiny-val-seed0.json"
    assert "is also an input of this command" in cli_error(evaluate_cli.main,
                                                           base + ["--out", clash])
    good = tmp_path / "r.json"
    evaluate_cli.main([str(a) for a in base + ["--out", good]])
    episodes = tmp_path / "episodes-tiny-val-seed0.json"
    before = sha(episodes)
    msg = cli_error(evaluate_cli.main, base[:-3] + ["--quiet", "--episodes", episodes,
                                                    "--out", episodes])
    assert "is also an input of this command" in msg and sha(episodes) == before
    assert "--out is empty" in cli_error(evaluate_cli.main, base + ["--out", ""])
    assert "--scenes is empty" in cli_error(
        evaluate_cli.main, ["--policy", "random", "--scenes", "", "--quiet"])


def test_evaluate_refuses_episode_counts_that_cannot_fit(tmp_path, tiny_dir, cli_error):
    msg = cli_error(evaluate_cli.main, ["--policy", "random", "--scenes", tiny_dir,
                                        "--episodes-per-room-type", "1000000000",
                                        "--out", tmp_path / "r.json"])
    assert "--episodes-per-room-type 1,000,000,000" in msg and "available" in msg
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------ 0 and empty values

def test_tpn_lr_zero_is_kept_and_both_stages_are_checked_first(tmp_path, cli_error,
                                                               monkeypatch):
    args = train_cli.parser().parse_args(["--preset", "baseline_tpn", "--tpn-lr", "0"])
    assert train_cli.pipeline_tpn_fields(args) == {"tpn_lr": 0.0}
    args = train_cli.parser().parse_args(["--preset", "full", "--tpn-episodes", "64"])
    assert train_cli.pipeline_tpn_fields(args) == {"total_episodes": 64}
    monkeypatch.chdir(tmp_path)
    msg = cli_error(train_cli.main, ["--preset", "tiny", "--tpn-lr", "0"])
    assert "--tpn-lr and --tpn-episodes go with the presets" in msg
    for flag, value, expect in (("--tpn-lr", "-1", "--tpn-lr: -1.0, expected"),
                                ("--tpn-episodes", "0", "--tpn-episodes: 0, expected")):
        msg = cli_error(train_cli.main, ["--preset", "full", flag, value,
                                         "--run-dir", tmp_path / "run"])
        assert expect in msg
    assert not (tmp_path / "run").exists() and not (tmp_path / "runs").exists()


def test_presets_have_distinct_default_run_directories():
    from orgnav_jax.training.config import TRAIN_PRESETS, get_config
    dirs = {name: get_config(name).run_dir for name in TRAIN_PRESETS}
    assert len(set(dirs.values())) == len(dirs), dirs
    assert dirs["small"] == "runs/baseline-calibrated" and dirs["baseline"] == "runs/baseline"


# ------------------------------------------------------------------ the coordinator

@pytest.mark.parametrize("address", ["localhost:notaport", "localhost", ":1234",
                                     "node0:0", "node0:70000", "no de:1234"])
def test_a_malformed_coordinator_is_one_line(address, cli_error):
    msg = cli_error(train_cli.main, ["--preset", "tiny", "--coordinator", address,
                                     "--num-processes", "2", "--process-id", "0"])
    assert f"--coordinator {address!r}: expected HOST:PORT" in msg


def test_a_silent_coordinator_times_out_with_a_message(cli_error, capsys):
    import socket
    with socket.socket() as s:           # a free port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    msg = cli_error(train_cli.main, ["--preset", "tiny", "--coordinator",
                                     f"127.0.0.1:{port}", "--num-processes", "2",
                                     "--process-id", "1", "--distributed-timeout", "1"])
    assert f"the coordinator at 127.0.0.1:{port} did not answer within 1 s" in msg
    assert "--distributed-timeout 0: expected an integer >= 1" in cli_error(
        train_cli.main, ["--distributed-timeout", "0", "--coordinator", "a:1",
                         "--num-processes", "2", "--process-id", "1"])


def test_evaluation_output_names_do_not_double(tmp_path, tiny_dir, monkeypatch):
    """runs/eval/<run>-<split>.json for a run on its own scenes; the scenes' name is added
    for named policies and for a run evaluated on other scenes."""
    import dataclasses
    from orgnav_jax import api, evaluation
    monkeypatch.chdir(tmp_path)
    run = api.LoadedPolicy(evaluation.random_policy(), None, "myrun", "tiny", tiny_dir,
                           from_run=True)
    kw = dict(per_room_type=2, progress=False)
    assert api.evaluate(run, "val", **kw)["out"] == "runs/eval/myrun-val.json"
    assert api.evaluate(run, "val", scenes_dir=tiny_dir, **kw)["out"] == \
        f"runs/eval/myrun-{Path(tiny_dir).name}-val.json"
    named = dataclasses.replace(run, name="random", from_run=False)
    assert api.evaluate(named, "val", **kw)["out"] == \
        f"runs/eval/random-{Path(tiny_dir).name}-val.json"


def test_scenes_info_takes_a_preset_name(tmp_path, monkeypatch, capsys, cli_error):
    from orgnav_jax.scenes.__main__ import main as scenes_main
    monkeypatch.setenv("ORGNAV_CACHE", str(tmp_path))
    assert scenes_main(["info", "tiny"]) == 0
    out = capsys.readouterr().out
    assert f"preset tiny, seed 0: {tmp_path / 'scenes-tiny-seed0-v'}" in out
    assert "16 rooms" in out
    msg = cli_error(scenes_main, ["info", "nope"])
    assert ("expected a SceneSet directory or a preset name "
            f"({', '.join(sorted(SCENE_PRESETS))})") in msg


def test_evaluate_names_the_split_it_printed(tmp_path, tiny_dir, capsys):
    evaluate_cli.main(["--policy", "random", "--scenes", tiny_dir, "--split", "val",
                       "--episodes-per-room-type", "2", "--quiet",
                       "--out", str(tmp_path / "r.json")])
    assert capsys.readouterr().out.startswith("val split, 8 episodes (unseen rooms):")


def test_per_target_success_sums_to_the_overall(tmp_path, tiny_dir, capsys):
    result = evaluate_cli.main(["--policy", "random", "--scenes", tiny_dir, "--split", "val",
                                "--episodes-per-room-type", "100", "--quiet", "--per-target",
                                "--out", str(tmp_path / "r.json")])
    per, overall = result["per_target"], result["overall"]
    assert sum(m["episodes"] for m in per.values()) == overall["episodes"]
    weighted = sum(m["success"] * m["episodes"] for m in per.values()) / overall["episodes"]
    assert weighted == pytest.approx(overall["success"])
    out = capsys.readouterr().out
    assert "per target category (episodes):" in out
    assert all(f"{t} ({m['episodes']})" in out for t, m in per.items())


def test_empty_or_negative_values_are_refused_not_dropped(tmp_path, cli_error):
    from orgnav_jax.scenes.__main__ import main as scenes_main
    assert "--coordinator is empty" in cli_error(
        train_cli.main, ["--coordinator", "", "--num-processes", "2", "--process-id", "0"])
    msg = cli_error(scenes_main, ["import", "--offline-dir", tmp_path, "--out",
                                  tmp_path / "o", "--detection-rows", ""])
    assert "--detection-rows '': expected comma-separated class names" in msg
    msg = cli_error(scenes_main, ["export", "--preset", "tiny", "--out", tmp_path / "e",
                                  "--episodes-per-type", "-1"])
    assert "--episodes-per-type -1: expected an integer >= 0" in msg
    assert not (tmp_path / "o").exists() and not (tmp_path / "e").exists()


def test_the_default_run_is_named_after_its_model_and_scenes():
    """Issue 67: `python -m orgnav_jax.train` trained on the calibrated benchmark but
    wrote runs/small and printed its row as `small`, the other scene preset's name. The
    run directory (and the row, its name) says what it is; a preset on scenes other than
    its own says which."""
    from orgnav_jax import train as train_cli
    from orgnav_jax.training.config import get_config
    assert train_cli.nav_config(train_cli.parser().parse_args([])).run_dir == \
        "runs/baseline-calibrated"
    for argv, run_dir in ((["--scene-preset", "small"], "runs/baseline-small"),
                          (["--preset", "we", "--scene-preset", "small"], "runs/we-small"),
                          (["--preset", "we"], "runs/we"),
                          (["--preset", "tiny"], "runs/tiny"),
                          (["--preset", "full", "--scene-preset", "small"], "runs/full-small"),
                          (["--scene-preset", "small", "--run-dir", "mine"], "mine")):
        assert train_cli.nav_config(train_cli.parser().parse_args(argv)).run_dir == run_dir
    assert get_config("tiny", scenes_dir="data/t4").run_dir == "runs/tiny-t4"
