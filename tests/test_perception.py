"""The perception knobs (scenes/synthetic/perception.py): each one's effect on a room's
arrays, their ranges, and that the defaults change nothing. No learning here."""

import dataclasses

import numpy as np
import pytest

from orgnav_jax.constants import CATEGORIES, NUM_CATEGORIES
from orgnav_jax.scenes.synthetic import builder, geometry, global_view, layout
from orgnav_jax.scenes.synthetic.perception import (
    CONFUSABLE, Perception, degrade_global, parse_knobs,
)
from orgnav_jax.scenes.synthetic.presets import get_preset

FP = 2          # one kitchen: many categories, ~2,000 states


@pytest.fixture(scope="module")
def room():
    return layout.generate_room(0, FP)


@pytest.fixture(scope="module")
def clean_codes(room):
    return global_view.global_codes(room, geometry.reachable_cells(room.reachable))


def _detections(room, **knobs):
    cells = geometry.reachable_cells(room.reachable)
    return builder.room_detections(room, 0, cells, geometry.state_poses(cells),
                                   Perception(**knobs))


@pytest.fixture(scope="module")
def clean(room):
    return _detections(room)


def _hit_category(codes):
    """(M,) category of the object each cell's ray hit (-1: not an object), read from the
    clean code's category embedding (channels 9-11)."""
    emb = np.asarray(global_view.CATEGORY_EMBED)
    cells = codes.reshape(-1, codes.shape[-1])
    is_obj = cells[:, 3] > 0.5
    d = ((cells[:, None, 9:12] - emb[None]) ** 2).sum(-1)
    return np.where(is_obj, d.argmin(1), -1)


def _readout_accuracy(x, y):
    """Training accuracy of the least-squares linear read-out of one-hot(y) from x."""
    X = np.concatenate([x, np.ones((len(x), 1))], 1).astype(np.float64)
    Y = np.eye(y.max() + 1)[y]
    W, *_ = np.linalg.lstsq(X, Y, rcond=None)
    return float(((X @ W).argmax(1) == y).mean())


def test_defaults_change_nothing(room, clean, clean_codes):
    ra = builder.room_arrays(0, FP, "train", room=room)
    np.testing.assert_array_equal(ra.global_feat, clean_codes)
    for got, want in zip((ra.det_box, ra.det_conf, ra.appearance), clean[2:]):
        np.testing.assert_array_equal(got, want)
    assert get_preset("small").perception == Perception()


@pytest.mark.parametrize("labels", ["furniture", "none"])
def test_global_labels_hide_the_object_category(clean_codes, labels):
    cat = _hit_category(clean_codes)
    obj = cat >= 0
    y = np.unique(cat[obj], return_inverse=True)[1]
    x_clean = clean_codes.reshape(-1, clean_codes.shape[-1])[obj]
    clean_acc = _readout_accuracy(x_clean, y)
    out = degrade_global(clean_codes, Perception(global_labels=labels),
                         np.random.default_rng(0))
    x = out.reshape(-1, out.shape[-1])[obj]
    majority = np.bincount(y).max() / len(y)
    assert clean_acc > 0.85 and _readout_accuracy(x, y) < majority + 0.1, (clean_acc, majority)
    # besides depth (channel 5) every object cell reads the same: no read-out can tell
    assert len(np.unique(np.delete(x, 5, axis=1), axis=0)) == 1
    np.testing.assert_array_equal(out[..., 9:12], 0.0)
    assert (out[..., 6:9] == 0).all() == (labels == "none")
    np.testing.assert_array_equal(out[..., :6], clean_codes[..., :6])   # geometry kept


def test_global_noise_and_room_style(clean_codes):
    rng = np.random.default_rng(0)
    noisy = degrade_global(clean_codes, Perception(global_noise=0.5), rng) - clean_codes
    assert abs(noisy.std() - 0.5) < 0.01 and abs(noisy.mean()) < 0.01
    styled = degrade_global(clean_codes, Perception(room_style=1.0), rng) - clean_codes
    offset = styled.reshape(-1, styled.shape[-1])
    np.testing.assert_allclose(offset, offset[:1].repeat(len(offset), 0), atol=1e-6)
    assert np.abs(offset[0]).max() > 0.05                       # one offset for the room


def _seen_rate(seen, conf, room):
    """Share of (state, category) pairs with a seen instance that are detected."""
    seen_cat = np.zeros(conf.shape, bool)
    for k, c in enumerate(room.obj_category):
        seen_cat[:, c] |= seen[:, k]
    return (conf[seen_cat] > 0).mean()


def test_recall_knobs_lower_recall(room, clean):
    seen = clean[0]
    base = _seen_rate(seen, clean[3], room)
    for knobs in ({"peak_recall": 0.5}, {"detect_range_scale": 0.5},
                  {"min_box_area": 400.0}):
        _, _, box, conf, _ = _detections(room, false_positive_rate=0.0, **knobs)
        assert _seen_rate(seen, conf, room) < base - 0.05, knobs
    _, _, box, conf, _ = _detections(room, false_positive_rate=0.0, min_box_area=400.0)
    area = (box[..., 2] - box[..., 0]) * (box[..., 3] - box[..., 1])
    assert (area[conf > 0] >= 400.0).all()


def test_false_positives_and_their_confidence(room, clean):
    present = np.zeros(NUM_CATEGORIES, bool)
    present[room.obj_category] = True
    _, _, _, conf, code = _detections(room, false_positive_rate=0.2, fp_confidence_max=0.9)
    fp = conf[:, ~present]                    # absent categories: false positives only
    assert 0.15 < (fp > 0).mean() < 0.25
    assert fp.max() > 0.8 and (clean[3][:, ~present] <= 0.35).all()


def test_confidence_noise_and_appearance_noise(room, clean):
    _, _, _, conf, code = _detections(room, confidence_noise=0.3, appearance_noise=2.0)
    both = (conf > 0) & (clean[3] > 0)
    assert np.abs(conf[both] - clean[3][both]).mean() > 0.05
    spread = lambda c: np.linalg.norm(c[clean[3] > 0], axis=-1).mean()
    assert spread(code) > 1.5 * spread(clean[4])


def test_confusion_moves_detections_to_a_similar_category(room, clean):
    present = np.zeros(NUM_CATEGORIES, bool)
    present[room.obj_category] = True
    _, _, box, conf, code = _detections(room, confusion=0.5, false_positive_rate=0.0)
    index = {c: i for i, c in enumerate(CATEGORIES)}
    group_of = {index[c]: {index[o] for o in g} for g in CONFUSABLE for c in g}
    clean_fp0 = _detections(room, false_positive_rate=0.0)[3]
    moved = (conf > 0) & (clean_fp0 == 0)
    assert moved.any()
    for c in np.flatnonzero(moved.any(0)):     # every new row is a similar category's
        assert c in group_of and group_of[c] & set(np.flatnonzero(present)), CATEGORIES[c]
    assert (conf > 0).sum() < (clean_fp0 > 0).sum()      # some land on a kept detection
    assert ((box != 0).any(-1) == (conf > 0)).all() and ((code != 0).any(-1) <= (conf > 0)).all()


def test_box_jitter(room, clean):
    _, _, box, conf, _ = _detections(room, box_jitter=10.0)
    on = conf > 0
    np.testing.assert_array_equal(on, clean[3] > 0)
    diff = box[on] - clean[2][on]
    assert 3.0 < np.abs(diff).mean() < 12.0
    assert (box[..., 2:] >= box[..., :2]).all()


@pytest.mark.parametrize("knobs", [{"global_labels": "some"}, {"confusion": 1.5},
                                   {"global_noise": -1.0}, {"peak_recall": True},
                                   {"fp_confidence_max": 0.0}])
def test_bad_knob_values(knobs):
    with pytest.raises(ValueError, match="perception knob") as err:
        Perception(**knobs)
    assert "\n" not in str(err.value)


def test_parse_knobs():
    assert parse_knobs(["global_labels=none", "confusion=0.2"]) == {
        "global_labels": "none", "confusion": 0.2}
    for bad in (["confusion"], ["colour=1"], ["confusion=high"]):
        with pytest.raises(ValueError, match="perception knob"):
            parse_knobs(bad)


def test_cli_refuses_bad_knobs_before_writing(tmp_path, capsys):
    from orgnav_jax.errors import run_cli
    from orgnav_jax.scenes.cli import main
    out = tmp_path / "set"
    argv = ["build", "--preset", "tiny", "--out", str(out), "--perception", "confusion=2"]
    assert run_cli(main, argv) == 2 and not out.exists()
    assert "confusion" in capsys.readouterr().err


def test_knobs_recorded_in_the_set_info():
    p = get_preset("tiny", num_rooms=1,
                   perception=dataclasses.replace(Perception(), confusion=0.1))
    info = dict(builder.build(p, 0).info)
    assert info["perception.confusion"] == 0.1
    assert not any(k.startswith("perception.") for k, _ in builder.build("tiny", 0, num_rooms=1).info)


def test_calibrated_presets_are_the_chosen_calibration_settings():
    from orgnav_jax.tables import calibration
    small = get_preset("small")
    for name, setting in (("calibrated", calibration.CHOSEN),
                          ("calibrated_22m", calibration.CHOSEN_22M)):
        preset = get_preset(name)
        assert preset.perception.changed() == calibration.SETTINGS[setting]
        # `small`'s rooms and splits; the episodes those the setting was calibrated on
        assert dataclasses.replace(preset, name="small", perception=Perception()) == \
            get_preset(small, episode_distance=calibration.episode_distance(setting))


def test_every_entry_point_defaults_to_the_calibrated_preset():
    """One default scene preset (constants.DEFAULT_SCENE_PRESET) behind the trainer, the
    evaluator, the scenes CLI, the gymnax env and the API."""
    import inspect
    from orgnav_jax import api, evaluate, gymnax_env, scenes
    from orgnav_jax.constants import DEFAULT_SCENE_PRESET
    from orgnav_jax.training.config import get_config
    assert DEFAULT_SCENE_PRESET == "calibrated"
    # evaluate's --scene-preset defaults to None: the policy's (LoadedPolicy's default,
    # or a run's own); given, it is compared with the run's (issue 67)
    assert evaluate.parser().get_default("preset") is None
    defaults = [get_config().scene_preset, api.LoadedPolicy(None, None, "x").scene_preset]
    defaults += [inspect.signature(f).parameters[name].default for f, name in (
        (api.evaluate_policy, "scene_preset"), (gymnax_env.make, "scene_preset"),
        (scenes.build, "preset"), (scenes.load_or_build, "preset"),
        (scenes.load_scenes, "preset"), (scenes.device_split, "preset"))]
    assert defaults == [DEFAULT_SCENE_PRESET] * len(defaults)
