"""The scene-preset knob episode_distance (per room type, the (min, max) optimal path
length of the seeded evaluation episodes) and the path-length statistics
(episodes.length_stats, `python -m orgnav_jax.scenes episodes`)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from orgnav_jax import scenes
from orgnav_jax.constants import ROOM_TYPES
from orgnav_jax.episodes import length_stats, sample_episodes
from orgnav_jax.errors import run_cli
from orgnav_jax.scenes.cli import main as scenes_main
from orgnav_jax.scenes.summary import summarize
from orgnav_jax.scenes.synthetic.builder import preset_info
from orgnav_jax.scenes.synthetic.cache import definition_mismatch
from orgnav_jax.scenes.synthetic.presets import (
    SCENE_PRESETS, episode_bounds, get_preset, parse_episode_distance)

# sha256 (first 16 hex) of tiny's episodes (50 per room type, seed 0) per split, as
# sample_episodes drew them before the knob existed (commit ce78206)
TINY_EPISODES = {"train": "d55db53557f4d0a9", "val": "441f653f9c489e51",
                 "test": "b5fa500a160d570d"}


def digest(episodes) -> str:
    h = hashlib.sha256()
    for k in ("scene", "start", "target", "optimal_len", "room_type"):
        h.update(np.ascontiguousarray(getattr(episodes, k)).tobytes())
    return h.hexdigest()[:16]


def with_knob(tiny_scenes, **bounds) -> scenes.SceneSet:
    """tiny_scenes as build('tiny', 0, episode_distance=bounds) records it (the knob acts
    only on the episode sampler: the arrays are the same)."""
    return tiny_scenes.replace(info=preset_info(get_preset("tiny", episode_distance=bounds), 0))


def test_the_default_leaves_every_preset_its_definition_and_episodes(tiny_scenes):
    bounded = {n for n, p in SCENE_PRESETS.items() if p.episode_distance is not None}
    assert bounded == {"calibrated_22m"}         # the one preset defined with bounds
    for name, preset in SCENE_PRESETS.items():
        if name in bounded:
            continue
        assert not any(k.startswith("episode_distance") for k, _ in preset_info(preset, 0))
        # naming today's bounds is the default: the same preset, info and cache check
        same = get_preset(name, episode_distance={"kitchen": (1, None)})
        assert same == preset and preset_info(same, 0) == preset_info(preset, 0)
    assert definition_mismatch(tiny_scenes, get_preset("tiny"), 0) == []
    for split, want in TINY_EPISODES.items():
        view = tiny_scenes.split_view(split)
        assert digest(sample_episodes(view, 50, seed=0, split=split)) == want


def test_a_set_of_another_episode_distance_is_another_definition(tiny_scenes, tmp_path):
    knob = get_preset("tiny", episode_distance={"bathroom": (3, None), "kitchen": (1, 9)})
    assert definition_mismatch(tiny_scenes, knob, 0) == [
        "episode_distance.kitchen not recorded, expected (1, 9)",
        "episode_distance.bathroom not recorded, expected (3, None)"]
    scenes.save(with_knob(tiny_scenes, bathroom=(3, None), kitchen=(1, 9)), tmp_path / "k")
    loaded = scenes.load(tmp_path / "k")          # (the bounds survive JSON: null, lists)
    assert definition_mismatch(loaded, knob, 0) == []
    assert episode_bounds(loaded.info)["bathroom"] == (3, None)
    assert definition_mismatch(loaded, get_preset("tiny"), 0)[0].startswith(
        "episode_distance.kitchen (1, 9), expected (1, None) (the default")


def test_the_knob_moves_the_mean_path_length_and_bounds_every_episode(tiny_scenes):
    base = length_stats(sample_episodes(tiny_scenes, 200, seed=0))
    longer = sample_episodes(with_knob(tiny_scenes, bathroom=(3, None), bedroom=(5, None)),
                             200, seed=0)
    shorter = sample_episodes(with_knob(tiny_scenes, kitchen=(1, 4)), 200, seed=0)
    for episodes, room, lo, hi in ((longer, "bathroom", 3, 99), (longer, "bedroom", 5, 99),
                                   (shorter, "kitchen", 1, 4)):
        length = episodes.optimal_len[episodes.room_type == ROOM_TYPES.index(room)]
        assert lo <= length.min() and length.max() <= hi, room
    assert length_stats(longer)["bathroom"]["mean"] > base["bathroom"]["mean"] + 0.5
    assert length_stats(longer)["bedroom"]["mean"] > base["bedroom"]["mean"] + 0.5
    assert length_stats(shorter)["kitchen"]["mean"] < base["kitchen"]["mean"] - 0.5
    for room in ("kitchen", "living_room"):      # the other room types keep their draws
        assert length_stats(longer)[room] == base[room]
    with pytest.raises(ValueError, match="bathroom rooms .*at distance 40..50$"):
        sample_episodes(with_knob(tiny_scenes, bathroom=(40, 50)), 5)


def test_episodes_may_start_with_the_target_in_view(tiny_scenes):
    """min 0 (the knob) or min_dist=0 (the sampler's argument, where the preset bounds
    none) draws episodes whose target is in view at the start (optimal_len 0), as the
    authors' episodes have (docs/calibrated.md); the default never does."""
    assert sample_episodes(tiny_scenes, 200, seed=0).optimal_len.min() == 1
    for episodes in (sample_episodes(tiny_scenes, 200, seed=0, min_dist=0),
                     sample_episodes(with_knob(tiny_scenes, **{r: (0, None) for r in
                                                                ROOM_TYPES}), 200, seed=0)):
        assert (episodes.optimal_len == 0).any()
    bounded = sample_episodes(with_knob(tiny_scenes, kitchen=(0, 0)), 50, seed=0)
    assert (bounded.optimal_len[bounded.room_type == 0] == 0).all()


@pytest.mark.parametrize("value, message", [
    ({"kitchen": (-1, None)}, r"episode_distance\['kitchen'\] \(-1, None\), expected "
                              "integers 0 <= min <= max"),
    ({"bedroom": (5, 3)}, r"episode_distance\['bedroom'\] \(5, 3\)"),
    ({"bathroom": (2.5, None)}, r"episode_distance\['bathroom'\] \(2.5, None\)"),
    ({"bathroom": 4}, r"episode_distance\['bathroom'\] 4, expected \(min, max\)"),
    ({"garage": (1, 2)}, r"episode_distance: unknown room type\(s\) \['garage'\]"),
    (7, r"episode_distance 7, expected \{room type: \(min, max\)\}"),
])
def test_a_bad_value_is_one_line_naming_the_field(value, message):
    with pytest.raises(ValueError, match="preset 'tiny': " + message) as err:
        get_preset("tiny", episode_distance=value)
    assert "\n" not in str(err.value)


def test_the_cli_builds_with_the_knob_and_refuses_bad_items(tmp_path, capsys):
    assert parse_episode_distance(["living_room=6", "kitchen=1:18"]) == {
        "living_room": (6, None), "kitchen": (1, 18)}
    for bad in (["garage=3"], ["bathroom"], ["bathroom=x:4"], ["bedroom=3", "bedroom=4"]):
        with pytest.raises(ValueError, match="episode_distance .*expected ROOM=MIN"):
            parse_episode_distance(bad)
    out = tmp_path / "bad"
    argv = ["build", "--preset", "tiny", "--num-rooms", "4", "--out", str(out),
            "--episode-distance", "bedroom=5:3"]
    assert run_cli(scenes_main, argv) == 2 and not out.exists()
    assert "episode_distance['bedroom'] (5, 3)" in capsys.readouterr().err
    out = tmp_path / "knob"
    assert scenes_main(["build", "--preset", "tiny", "--num-rooms", "4", "--out", str(out),
                        "--episode-distance", "bathroom=2"]) == 0
    assert episode_bounds(scenes.load(out).info)["bathroom"] == (2, None)
    assert summarize(scenes.load(out))["episode_distance"] == {"bathroom": [2, None]}
    capsys.readouterr()
    assert scenes_main(["info", str(out)]) == 0
    assert "(moves) bounded: bathroom 2.." in capsys.readouterr().out


def test_the_episodes_command_prints_length_stats(tiny_dir, capsys):
    assert scenes_main(["episodes", tiny_dir, "--episodes-per-room-type", "20", "--json"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    stats = json.loads(lines[-1])
    view = scenes.load(tiny_dir).split_view("test")
    assert stats["test"] == length_stats(sample_episodes(view, 20, seed=0, split="test"))
    assert set(stats) == {"val", "test"} and stats["val"]["all"]["episodes"] == 80
    assert lines[1].split() == ["split", *ROOM_TYPES, "all"]
    mean, median = stats["val"]["kitchen"]["mean"], stats["val"]["kitchen"]["median"]
    assert lines[2].split()[:4] == ["val", f"{mean:.2f}", "/", f"{median:g}"]
