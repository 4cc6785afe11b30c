"""The flat (unpadded) SceneSet layout (issue 14).

- gathers, env steps and the env's random starts on ragged rooms equal the padded
  layout's results (a padded reference built here with flat.to_padded, indexed by
  (scene, local state) as the format-1 code did);
- episodes keep local state indices: sampled sets and episode files are those of the
  padded layout;
- a split view of a memory-mapped set holds only its rooms' states (a view of the map,
  nothing copied); other selections gather only their rows; to_device copies writable
  arrays; the process cache shares one loaded set and one device copy per split;
- format-1 (padded) sets on disk: read (converted, with a warning naming `convert`) and
  converted by `python -m orgnav_jax.scenes convert`;
- int8 features: round trip within the quantization error, decoded inside jit; a set
  with int8 features and no scale is refused.
"""

from __future__ import annotations

import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from test_storage import assert_same_sceneset

from orgnav_jax import constants as K
from orgnav_jax import env
from orgnav_jax import scenes as S
from orgnav_jax.episodes import sample_episodes, save_episodes
from orgnav_jax.scenes.synthetic import cache
from orgnav_jax.scenes.sceneset import storage
from orgnav_jax.scenes.__main__ import main
from orgnav_jax.scenes.sceneset.flat import padded_valid, to_padded
from orgnav_jax.scenes.sceneset.keys import state_key
from orgnav_jax.scenes.sceneset.quantize import quantize_features
from orgnav_jax.scenes.sceneset.fields import PER_STATE_FIELDS, UNREACHABLE


@pytest.fixture(scope="module")
def train(tiny_scenes):
    """8 rooms of 912..5792 states: ragged."""
    v = tiny_scenes.split_view("train")
    assert len(set(np.asarray(v.state_count).tolist())) > 4
    return v


class Padded:
    """The padded layout of a SceneSet (N, S_max, ...), as format 1 stored it."""

    def __init__(self, scenes):
        self.count = np.asarray(scenes.state_count)
        self.valid = padded_valid(scenes)
        fill = {"dist": UNREACHABLE, "expert_action": -1}
        for name in PER_STATE_FIELDS:
            setattr(self, name, to_padded(scenes, name, fill.get(name, 0)))
        self.targets = np.asarray(scenes.targets)


def _flat_to_local(scenes, state):
    """Global flat indices -> (scene, local index)."""
    n = scenes.state_scene[state]
    return n, state - np.asarray(scenes.state_offset)[n]


# ----------------------------------------------------------- ragged == padded
@pytest.mark.parametrize("view", ["train", "select"])
def test_gathers_and_env_steps_equal_the_padded_layout(tiny_scenes, train, view):
    scenes = train if view == "train" else tiny_scenes.select([9, 0, 14, 5])  # re-based
    pad, dev = Padded(scenes), scenes.to_device()
    params = env.EnvParams()
    keys = jax.random.split(jax.random.PRNGKey(11), 64)
    _, st = jax.vmap(env.reset, in_axes=(0, None, None))(keys, dev, params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None, None)), static_argnums=4)
    gather = jax.jit(S.gather_features)
    rng = np.random.default_rng(0)
    n, s = _flat_to_local(scenes, np.asarray(st.state))
    np.testing.assert_array_equal(n, np.asarray(st.scene))
    for t in range(40):
        # features and observations by global index == the padded arrays at (n, s)
        glob, app, box, conf = gather(dev, st.state)
        code_g = pad.global_feat[n, s].astype(np.float32)
        np.testing.assert_allclose(np.asarray(glob),
                                   np.maximum(code_g @ np.asarray(scenes.global_basis), 0),
                                   rtol=1e-4, atol=1e-4)
        np.testing.assert_array_equal(np.asarray(conf), pad.det_conf[n, s].astype(np.float32))
        np.testing.assert_array_equal(np.asarray(box), pad.det_box[n, s].astype(np.float32))
        assert np.asarray(app).shape == (64, K.NUM_CATEGORIES, scenes.appearance_dim)
        obs = jax.vmap(env.observe, in_axes=(0, None))(st, dev)
        np.testing.assert_array_equal(np.asarray(obs.det_box), pad.det_box[n, s])
        assert pad.valid[n, s].all()
        target = np.asarray(st.target)
        expert = np.asarray(dev.expert_action[st.state, st.target])
        np.testing.assert_array_equal(expert, pad.expert_action[n, s, target])
        a = rng.integers(0, K.NUM_ACTIONS, 64)
        a = np.where(rng.random(64) < 0.5, np.maximum(expert, 0), a).astype(np.int32)
        _, st2, reward, done, info = step(jax.random.split(keys[t % 64], 64), st,
                                          jnp.asarray(a), dev, params)
        # the padded transition, success and optimal length at the same (n, s)
        want_next = pad.next_state[n, s, a]
        success = (a == K.DONE) & pad.visible[n, s, target]
        np.testing.assert_array_equal(np.asarray(info["success"]), success)
        np.testing.assert_array_equal(np.asarray(info["failed"]),
                                      (want_next == s) & (a != K.DONE))
        np.testing.assert_array_equal(np.asarray(reward),
                                      np.where(success, params.success_reward,
                                               params.step_penalty).astype(np.float32))
        done = np.asarray(done)
        n2, s2 = _flat_to_local(scenes, np.asarray(st2.state))
        np.testing.assert_array_equal(s2[~done], want_next[~done])
        np.testing.assert_array_equal(n2[~done], n[~done])
        # fresh episodes: optimal length = the padded dist at the local start
        np.testing.assert_array_equal(np.asarray(st2.optimal_len)[done],
                                      pad.dist[n2, s2, np.asarray(st2.target)][done])
        st, n, s = st2, n2, s2


def test_random_starts_are_bits_mod_count_as_before(train):
    """sample_episode draws the same local starts as the padded layout did: bits % count
    of the room (then state_offset is added by start_episode)."""
    dev, pad, params = train.to_device(), Padded(train), env.EnvParams()
    for seed in range(20):
        key = jax.random.PRNGKey(seed)
        scene, start, target = env.sample_episode(key, dev, params)
        bits = np.asarray(jax.random.bits(key, (env.START_TRIES + 2,), jnp.uint32))
        n = int(bits[0] % train.num_scenes)
        starts = (bits[1:env.START_TRIES + 1] % np.uint32(pad.count[n])).astype(np.int64)
        assert int(scene) == n and int(start) in starts.tolist()
        far = pad.dist[n, starts] >= params.min_start_dist
        ok = pad.targets[n][None] & far
        pick = int(np.argmax(ok.any(1))) if ok.any() else env.START_TRIES - 1
        assert int(start) == starts[pick]
        state = env.start_episode(scene, start, target, dev, params)
        assert int(state.state) == int(train.state_offset[n]) + int(start)
        assert int(state.optimal_len) == pad.dist[n, int(start), int(target)]


def _padded_sample(pad, room_type, per_room_type, seed, min_dist=1):
    """The format-1 episode sampler, on padded arrays (episodes.sample_episodes before
    the flat layout)."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(len(K.ROOM_TYPES)):
        of_type = np.flatnonzero(room_type == t)
        made = 0
        while made < per_room_type:
            n = int(rng.choice(of_type))
            s = int(rng.integers(pad.count[n]))
            d = pad.dist[n, s].astype(np.int64)
            ok = np.flatnonzero(pad.targets[n] & (d >= min_dist) & (d < UNREACHABLE))
            if ok.size == 0:
                continue
            c = int(rng.choice(ok))
            out.append((n, s, c, int(d[c]), t))
            made += 1
    return np.asarray(out)


def test_episodes_and_episode_files_are_those_of_the_padded_layout(tiny_scenes, tmp_path):
    test = tiny_scenes.split_view("test")
    pad = Padded(test)
    eps = sample_episodes(test, per_room_type=30, seed=4, split="test")
    want = _padded_sample(pad, np.asarray(test.room_type), 30, 4)
    got = np.stack([eps.scene, eps.start, eps.target, eps.optimal_len, eps.room_type], 1)
    np.testing.assert_array_equal(got, want)          # local starts, as before
    path = tmp_path / "eps.json"
    save_episodes(path, eps, test)
    records = json.loads(path.read_text())["episodes"]
    assert [r["state"] for r in records] == [state_key(pad.pose[n, s]) for n, s in want[:, :2]]
    assert records[0]["scene"] == test.scene_names[want[0, 0]]


# ------------------------------------------------------------ views and copies
@pytest.fixture(scope="module")
def saved_tiny(tiny_scenes, tmp_path_factory):
    return S.save(tiny_scenes, tmp_path_factory.mktemp("tiny") / "set")


def test_split_view_of_a_memory_mapped_set_holds_only_its_rooms(tiny_scenes, saved_tiny):
    full = S.load(saved_tiny, mmap=True)
    assert isinstance(full.global_feat, np.memmap)
    total = 0
    for name in K.SPLITS:
        v = full.split_view(name)
        mine = np.asarray(full.split) == K.SPLIT_INDEX[name]
        rows = int(np.asarray(full.state_count)[mine].sum())
        total += rows
        for f in PER_STATE_FIELDS:
            arr, base = getattr(v, f), getattr(full, f)
            assert arr.shape[0] == rows == v.num_states < full.num_states, f
            if f == "next_state" and int(np.asarray(full.state_offset)[mine].min()) != 0:
                continue        # re-based global indices: a new (rows, 6) int32 array
            # a slice of the map: nothing copied, and only this split's bytes
            assert isinstance(arr, np.memmap) and np.shares_memory(arr, base), f
            start = arr.ctypes.data - base.ctypes.data
            assert start == int(np.asarray(full.state_offset)[mine].min()) * \
                (base.nbytes // base.shape[0]), f
            assert arr.nbytes == rows * (base.nbytes // base.shape[0]), f
        v.validate(name)
        assert_same_sceneset(v, tiny_scenes.split_view(name))
    assert total == full.num_states


def _resident_kb(file) -> int | None:
    """kB of `file` mapped and resident in this process (/proc/self/smaps), None if the
    system does not tell."""
    try:
        lines = open("/proc/self/smaps").read().splitlines()
    except OSError:
        return None
    total, inside = 0, False
    for line in lines:
        if "-" in line.split(" ")[0] and len(line.split()) >= 5:     # a mapping's header
            inside = line.split()[-1] == str(file)
        elif inside and line.startswith("Rss:"):
            total += int(line.split()[1])
    return total


def test_loading_memory_mapped_reads_features_without_keeping_them(saved_tiny):
    """Validation streams every feature through the map (finiteness) and releases the
    pages: after load(mmap=True) the features are not resident in the process."""
    file = (saved_tiny / "global_feat.npy").resolve()
    full = S.load(saved_tiny, mmap=True)
    kb = _resident_kb(file)
    if kb is None:
        pytest.skip("no /proc/self/smaps")
    assert full.global_feat.nbytes > 40e6
    assert kb * 1024 < 0.05 * full.global_feat.nbytes, kb
    np.asarray(full.split_view("val").global_feat).max()    # reading a view maps it in
    assert _resident_kb(file) * 1024 < 0.5 * full.global_feat.nbytes


def test_a_scattered_selection_gathers_only_its_rows(saved_tiny):
    full = S.load(saved_tiny, mmap=True)
    v = full.room_type_view("kitchen")                 # one room of each split: 3 runs
    rows = int(np.asarray(v.state_count).sum())
    assert v.global_feat.shape[0] == rows < full.num_states
    assert not np.shares_memory(v.global_feat, full.global_feat)  # its own rows only
    assert v.global_feat.nbytes == rows * full.global_feat.nbytes // full.num_states
    v.validate("kitchen")


def test_to_device_puts_each_array_once_and_copies_writable_arrays(train):
    dev = train.to_device()
    assert all(isinstance(x, jax.Array) for x in jax.tree_util.tree_leaves(dev))
    assert dev.to_device().dist is dev.dist             # device arrays are not put again
    writable = train.replace(dist=np.array(train.dist))
    d = writable.to_device()
    before = np.asarray(d.dist).copy()
    writable.dist[:] = 0                     # later writes never reach the device array
    np.testing.assert_array_equal(np.asarray(d.dist), before)


def test_process_cache_shares_one_set_and_one_device_copy_per_split(tiny_scenes, tmp_path):
    path = S.save(tiny_scenes.room_type_view("bathroom"), tmp_path / "bath")
    cache.clear_loaded()
    try:
        a = cache.load_scenes(scenes_dir=str(path))
        assert isinstance(a.global_feat, np.memmap) and cache.load_scenes(
            scenes_dir=str(path)) is a
        val = cache.device_split(scenes_dir=str(path), split="val")
        assert cache.device_split(scenes_dir=str(path), split="val") is val
        assert val.num_scenes == 1 and isinstance(val.global_feat, jax.Array)
        S.save(tiny_scenes.room_type_view("kitchen"), path)       # replaced on disk
        b = cache.load_scenes(scenes_dir=str(path))
        assert b is not a and b.scene_names == tiny_scenes.room_type_view("kitchen").scene_names
        assert cache.device_split(scenes_dir=str(path), split="val") is not val
    finally:
        cache.clear_loaded()


# ------------------------------------------------------------- format 1 on disk
def _write_format1(scenes, path):
    """The on-disk layout of format version 1 (written by the padded code): per-state
    fields (N, S_max, ...) padded (self-loops, UNREACHABLE, NO_ACTION, zeros), next_state
    in per-room indices, a state_valid mask, no state_offset."""
    path.mkdir(parents=True)
    fill = {"dist": UNREACHABLE, "expert_action": -1}
    arrays = {name: to_padded(scenes, name, fill.get(name, 0)) for name in PER_STATE_FIELDS}
    arrays["state_valid"] = padded_valid(scenes)
    for name in ("present", "targets", "state_count", "room_type", "scene_id", "split",
                 "appearance_proto", "appearance_basis", "global_basis"):
        if getattr(scenes, name) is not None:
            arrays[name] = np.asarray(getattr(scenes, name))
    fields = {}
    for name, arr in arrays.items():
        np.save(path / f"{name}.npy", arr)
        fields[name] = {"shape": list(arr.shape), "dtype": str(arr.dtype)}
    info = {k: list(v) if isinstance(v, tuple) else v for k, v in scenes.info}
    info["version"] = 1
    (path / storage.META_FILE).write_text(json.dumps(
        {"format": storage.FORMAT_NAME, "version": 1, "info": info, "fields": fields}))
    return path


def test_format1_sets_are_read_with_a_warning_naming_convert(tiny_scenes, tmp_path):
    old = _write_format1(tiny_scenes, tmp_path / "old")
    assert storage.is_scene_set(old)
    for mmap in (False, True):
        with pytest.warns(UserWarning, match=r"format version 1 .* python -m orgnav_jax\."
                                             r"scenes convert .* --out NEW"):
            back = S.load(old, mmap=mmap)
        assert_same_sceneset(back, tiny_scenes)       # identical to the flat build


def test_convert_command_rewrites_format1_and_quantizes(tiny_scenes, tmp_path, capsys):
    old = _write_format1(tiny_scenes.room_type_view("bathroom"), tmp_path / "old")
    new = tmp_path / "new"
    assert main(["convert", str(old), "--out", str(new)]) == 0
    assert "converted" in capsys.readouterr().out
    meta = json.loads((new / storage.META_FILE).read_text())
    assert meta["version"] == storage.FORMAT_VERSION == 2
    assert not (new / "state_valid.npy").exists() and (new / "state_offset.npy").exists()
    with warnings.catch_warnings():
        warnings.simplefilter("error")                # no old-format warning any more
        back = S.load(new, mmap=True)
    assert_same_sceneset(back, tiny_scenes.room_type_view("bathroom"))
    assert main(["convert", str(old), "--out", str(old), "--features", "int8"]) == 0
    q = S.load(old)                                   # replaced in place, int8
    assert q.global_feat.dtype == np.int8 and q.global_scale is not None
    assert not (old / "state_valid.npy").exists()


# ----------------------------------------------------------------------- int8
@pytest.fixture(scope="module")
def raw(tiny_scenes):
    """The bathrooms with their stored arrays as raw features (bases None), like an
    imported set."""
    return tiny_scenes.room_type_view("bathroom").replace(
        global_basis=None, appearance_basis=None, appearance_proto=None)


def test_int8_round_trip_within_the_quantization_error(raw, tmp_path):
    q = quantize_features(raw)
    q.validate("int8")
    assert q.global_feat.dtype == q.appearance.dtype == np.int8
    assert q.global_scale.shape == (raw.global_feat.shape[-1],)
    assert q.appearance_scale.shape == (raw.appearance.shape[-1],)
    assert q.global_feat.nbytes * 2 == raw.global_feat.nbytes
    for name, scale in (("global_feat", q.global_scale), ("appearance", q.appearance_scale)):
        x = np.asarray(getattr(raw, name), np.float32)
        back = np.asarray(getattr(q, name), np.float32) * scale
        assert (np.abs(back - x) <= scale / 2 + 1e-6).all(), name
    # decoded inside jit: the float16 set's features within the same error
    path = S.save(q, tmp_path / "q")
    loaded = S.load(path, mmap=True)
    assert loaded.global_feat.dtype == np.int8
    idx = jnp.arange(0, raw.num_states, 97)
    got = jax.jit(S.gather_features)(loaded.to_device(), idx)
    want = S.gather_features(raw.to_device(), idx)
    for g, w, scale in zip(got[:2], want[:2], (q.global_scale, q.appearance_scale)):
        assert (np.abs(np.asarray(g) - np.asarray(w)) <= scale / 2 + 1e-3).all()
    for g, w in zip(got[2:], want[2:]):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))   # boxes, confidences


def test_int8_codes_of_a_synthetic_set_decode_through_the_bases(train):
    q = quantize_features(train.room_type_view("bathroom"))
    idx = jnp.arange(0, q.num_states, 31)
    got = S.gather_features(q.to_device(), idx)
    want = S.gather_features(train.room_type_view("bathroom").to_device(), idx)
    scale = np.abs(np.asarray(q.global_scale) @ np.asarray(q.global_basis)).max()
    assert np.abs(np.asarray(got[0]) - np.asarray(want[0])).max() < 4 * scale


def test_int8_without_its_scale_is_refused(raw, tmp_path):
    q = quantize_features(raw)
    with pytest.raises(ValueError, match="field 'global_feat' is int8 but field "
                                         "'global_scale'.*missing"):
        q.replace(global_scale=None).validate()
    with pytest.raises(ValueError, match="'appearance_scale' is given but 'appearance' is "
                                         "float16"):
        raw.replace(appearance_scale=q.appearance_scale).validate()
    with pytest.raises(ValueError, match="'global_scale' holds values <= 0"):
        q.replace(global_scale=np.zeros_like(q.global_scale)).validate()
    path = S.save(q, tmp_path / "q")                  # on disk: scale file removed
    (path / "global_scale.npy").unlink()
    meta = json.loads((path / storage.META_FILE).read_text())
    del meta["fields"]["global_scale"]
    (path / storage.META_FILE).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="'global_scale'.*missing"):
        S.load(path)


def test_import_features_int8(tmp_path):
    from test_offline_handmade import write_scene

    from orgnav_jax.scenes.offline.importer import import_to
    write_scene(tmp_path / "offline")
    f16, _ = import_to(tmp_path / "offline", tmp_path / "f16")
    q, _ = import_to(tmp_path / "offline", tmp_path / "q", features="int8")
    loaded = S.load(tmp_path / "q")
    assert loaded.global_feat.dtype == loaded.appearance.dtype == np.int8
    back = np.asarray(loaded.global_feat, np.float32) * loaded.global_scale
    np.testing.assert_allclose(back, np.asarray(f16.global_feat, np.float32),
                               atol=float(loaded.global_scale.max()) / 2 + 1e-6)
    with pytest.raises(ValueError, match="features 'int4'"):
        import_to(tmp_path / "offline", tmp_path / "x", features="int4")
