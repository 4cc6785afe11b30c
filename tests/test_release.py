"""The authors' released networks (issue 39): the loader of their state dicts against a
numpy transcription of the release's forward (`models/basemodel.py`, `graphmodel.py`),
and each departure the parity check found, pinned so that it cannot come back. No torch:
state dicts are built here with the release's names and shapes (small widths)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax.models import release
from orgnav_jax.models.navmodel import NavCarry
from orgnav_jax.models.trunk import Trunk

G, D, C, H, F, E = 8, 12, 22, 16, 8, 10     # global, appearance, categories, hidden, fuse, action


def state_dict(kind: str, seed: int = 0, layers: int = 2) -> dict:
    """Random weights and biases with the release's names, at small widths."""
    rng = np.random.default_rng(seed)
    shapes = {"conv1.weight": (F, G, 1, 1), "conv1.bias": (F,),
              "embed_action.weight": (E, 6), "embed_action.bias": (E,),
              "pointwise.weight": (F, F + C + E, 1, 1), "pointwise.bias": (F,),
              "critic_linear_1.weight": (64, H), "critic_linear_1.bias": (64,),
              "critic_linear_2.weight": (1, 64), "critic_linear_2.bias": (1,),
              "actor_linear.weight": (6, H), "actor_linear.bias": (6,)}
    for i in range(layers):
        shapes.update({f"lstm.weight_ih_l{i}": (4 * H, 49 * F if i == 0 else H),
                       f"lstm.weight_hh_l{i}": (4 * H, H),
                       f"lstm.bias_ih_l{i}": (4 * H,), f"lstm.bias_hh_l{i}": (4 * H,)})
    if kind == "BaseModel":
        shapes.update({"detection_feature.weight": (49, D + 6), "detection_feature.bias": (49,)})
    else:
        shapes.update({"graph_detection_feature.0.weight": (32, D + 6),
                       "graph_detection_feature.0.bias": (32,),
                       "graph_detection_feature.2.weight": (49, 32),
                       "graph_detection_feature.2.bias": (49,)})
        for i in range(1, 6):
            shapes[f"graph_detection_other_info_linear_{i}.weight"] = (C, 6 if i == 1 else C)
            shapes[f"graph_detection_other_info_linear_{i}.bias"] = (C,)
    return {k: (rng.standard_normal(s) / np.sqrt(s[-1] if len(s) > 1 else 4)).astype(np.float32)
            for k, s in shapes.items()}


def reference_step(sd, kind, state, appear, info, ind, probs, h, c):
    """The release's forward for one sample (numpy transcription of its embedding() and
    a3clstm()): state (G, 7, 7), appear (C, D), info (C, 5), ind (C, 1), probs (6,),
    h, c (L, H) -> logits (6,), value (1,), h, c."""
    relu = lambda x: np.maximum(x, 0)
    lin = lambda name, x: x @ sd[f"{name}.weight"].T + sd[f"{name}.bias"]
    if kind == "BaseModel":
        t = relu(lin("detection_feature", np.concatenate([appear, info, ind], 1)))
    else:
        r = relu(lin("graph_detection_other_info_linear_1", np.concatenate([info, ind], 1))).T
        for i in range(2, 6):
            r = relu(lin(f"graph_detection_other_info_linear_{i}", r))
        new_appear = (appear.T @ r).T
        t = np.concatenate([new_appear, info, ind], 1)
        t = relu(lin("graph_detection_feature.2", relu(lin("graph_detection_feature.0", t))))
    conv = lambda name, x: (np.einsum("oi,ihw->ohw", sd[f"{name}.weight"][:, :, 0, 0], x)
                            + sd[f"{name}.bias"][:, None, None])
    a = np.broadcast_to(relu(lin("embed_action", probs))[:, None, None], (E, 7, 7))
    x = np.concatenate([relu(conv("conv1", state)), t.reshape(C, 7, 7), a], 0)
    x = relu(conv("pointwise", x)).reshape(-1)
    sig = lambda z: 1 / (1 + np.exp(-z))
    h, c = h.copy(), c.copy()
    for i in range(h.shape[0]):
        g = (sd[f"lstm.weight_ih_l{i}"] @ x + sd[f"lstm.bias_ih_l{i}"]
             + sd[f"lstm.weight_hh_l{i}"] @ h[i] + sd[f"lstm.bias_hh_l{i}"])
        gi, gf, gg, go = np.split(g, 4)
        c[i] = sig(gf) * c[i] + sig(gi) * np.tanh(gg)
        h[i] = sig(go) * np.tanh(c[i])
        x = h[i]
    return lin("actor_linear", x), lin("critic_linear_2", lin("critic_linear_1", x)), h, c


def release_inputs(rng, n: int):
    det = rng.random((n, C)) < 0.6
    probs = rng.dirichlet(np.ones(6), n).astype(np.float32)
    probs[0] = 0                                   # an episode's first step
    ind = np.zeros((n, C, 1), np.float32)
    ind[np.arange(n), rng.integers(0, C, n), 0] = 1
    return (rng.random((n, G, 7, 7)).astype(np.float32),
            (rng.random((n, C, D)) * det[..., None]).astype(np.float32),
            np.concatenate([rng.random((n, C, 4)) * det[..., None],
                            (rng.random((n, C)) * det)[..., None]], -1).astype(np.float32),
            ind, probs)


@pytest.mark.parametrize("kind", ["BaseModel", "GraphModel"])
def test_loaded_release_model_computes_the_release_forward(kind):
    """Two steps, hidden state carried: logits, value, h and c of every LSTM layer match
    the numpy transcription of the release (so every ReLU, the linear critic, the ORG
    wiring, 2 LSTM layers and the flattening order are as the release's)."""
    sd = state_dict(kind)
    net = release.load(kind, sd)
    rng = np.random.default_rng(1)
    state, appear, info, ind, probs = release_inputs(rng, 3)
    h = (0.5 * rng.standard_normal((2, 3, H))).astype(np.float32)
    c = (0.5 * rng.standard_normal((2, 3, H))).astype(np.float32)
    ours, ref = (h, c), [(h[:, i], c[:, i]) for i in range(3)]
    for _ in range(2):
        logits, value, ours = net.step(state, appear, info, ind, probs, ours)
        for i in range(3):
            r_logits, r_value, rh, rc = reference_step(sd, kind, state[i], appear[i], info[i],
                                                       ind[i], probs[i], *ref[i])
            ref[i] = (rh, rc)
            np.testing.assert_allclose(logits[i], r_logits, rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(value[i], r_value, rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(ours[0][:, i], rh, rtol=1e-4, atol=1e-5)
            np.testing.assert_allclose(ours[1][:, i], rc, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("change, message", [
    (lambda sd: sd.pop("pointwise.bias"), "missing parameter 'pointwise.bias'"),
    (lambda sd: sd.update({"extra.weight": np.zeros((2, 2), np.float32)}),
     "unexpected parameter 'extra.weight' for a BaseModel"),
    (lambda sd: sd.update({"actor_linear.weight": np.zeros((5, H), np.float32)}),
     r"'actor_linear.weight' has shape \(5, 16\), expected \(6, 16\)"),
    (lambda sd: sd.update({"lstm.weight_hh_l1": np.zeros((4 * H, H + 1), np.float32)}),
     r"'lstm.weight_hh_l1' has shape \(64, 17\), expected \(64, 16\)"),
    (lambda sd: sd.update({"conv1.weight": np.zeros((F, G, 3, 3), np.float32)}),
     "expected a 1x1 convolution"),
    (lambda sd: sd.update({"embed_action.bias": np.zeros((E,), np.int64)}),
     "expected a 1-d float array"),
])
def test_a_bad_state_dict_is_one_line_naming_the_parameter(change, message):
    sd = state_dict("BaseModel")
    change(sd)
    with pytest.raises(release.ReleaseError, match=message) as err:
        release.load("BaseModel", sd)
    assert "\n" not in str(err.value)
    with pytest.raises(release.ReleaseError, match="release kind 'Graph'"):
        release.load("Graph", sd)


def test_read_checkpoint_without_torch_or_file_is_one_line(tmp_path):
    with pytest.raises(release.ReleaseError) as err:
        release.read_checkpoint(tmp_path / "missing.dat")
    assert "missing.dat" in str(err.value) and "\n" not in str(err.value)


# ---- each departure of issue 39, pinned on the trunk itself ----------------------------

@pytest.fixture(scope="module")
def trunk_and_params():
    trunk = Trunk(glob_channels=F, action_embed=E, fuse_channels=F, hidden=H)
    glob = jnp.ones((2, 7, 7, G))
    carry = trunk.initial_carry(2)
    params = trunk.init(jax.random.PRNGKey(0), glob, jnp.zeros((2, C, 49)), jnp.zeros((2, 6)),
                        carry)
    return trunk, params, glob, carry


def test_release_trunk_relus_category_maps_and_action_embedding(trunk_and_params):
    """Negative category maps and a negative action embedding reach the LSTM as zeros."""
    trunk, params, glob, _ = trunk_and_params
    embed = lambda p, maps, prev: trunk.apply(p, glob, maps, prev, method=trunk.embed)
    maps = jax.random.normal(jax.random.PRNGKey(1), (2, C, 49))
    probs = jax.nn.softmax(jax.random.normal(jax.random.PRNGKey(2), (2, 6)))
    np.testing.assert_allclose(embed(params, maps, probs),
                               embed(params, jnp.maximum(maps, 0), probs), rtol=1e-6)
    assert not np.allclose(embed(params, maps, probs), embed(params, maps * 0, probs))
    neg = jax.tree_util.tree_map(lambda x: x, params)          # an embedding < 0 everywhere
    dense = neg["params"]["action_dense"]
    dense["kernel"], dense["bias"] = -jnp.abs(dense["kernel"]), -jnp.abs(dense["bias"]) - 0.1
    np.testing.assert_allclose(embed(neg, maps, probs), embed(neg, maps, 3 * probs), rtol=1e-6)
    assert not np.allclose(embed(params, maps, probs), embed(params, maps, 3 * probs))


def test_release_critic_is_affine_in_the_lstm_output(trunk_and_params):
    """The value recur returns is (h K1 + b1) K2 + b2 of its own LSTM output h."""
    trunk, params, _, carry = trunk_and_params
    p = params["params"]
    gates = 3 * jax.random.normal(jax.random.PRNGKey(2), (2, 4 * H))
    _, value, _, h = trunk.apply(params, gates, carry, method=trunk.recur)
    hidden = h @ p["critic_hidden"]["kernel"] + p["critic_hidden"]["bias"]
    assert (hidden < 0).any()                 # a ReLU between the layers would change it
    np.testing.assert_allclose(value, (hidden @ p["critic"]["kernel"] + p["critic"]["bias"])[:, 0],
                               rtol=1e-5, atol=1e-6)


def test_release_trunk_has_two_lstm_layers_and_two_dropout_sites(trunk_and_params):
    trunk, params, glob, carry = trunk_and_params
    assert trunk.lstm_layers == 2 and len(carry) == 2
    assert trunk.dropout_channels() == F + F
    maps = jax.random.normal(jax.random.PRNGKey(1), (2, C, 49))
    embed = lambda drop: trunk.apply(params, glob, maps, jnp.zeros((2, 6)), drop,
                                     method=trunk.embed)
    ones = jnp.ones((2, 7, 7, 2 * F))
    np.testing.assert_allclose(embed(ones), embed(None), rtol=1e-6)
    # everything after the fusion layer dropped: the LSTM sees zeros (its gates = bias)
    bias = params["params"]["lstm_0"]["bias"]
    np.testing.assert_allclose(embed(ones.at[..., F:].set(0.0)),
                               jnp.broadcast_to(bias, (2, 4 * H)), atol=1e-6)
    assert not np.allclose(embed(ones.at[..., :F].set(0.0)), embed(ones))


def test_release_init_gives_small_actor_logits_and_zero_biases():
    """The release's initialisation: each actor unit's weights have norm 0.01
    (norm_col_init), so unit-variance LSTM outputs give logits of std about 0.01 (flax's
    default gave ~1); every bias is 0; the global 1x1 kernel has the ReLU gain."""
    from orgnav_jax.models import build_model, init_params
    from orgnav_jax.scenes import load_scenes
    from orgnav_jax.training.config import get_config
    scenes = load_scenes("tiny", 0, None).split_view("train")
    params = init_params(build_model(get_config("tiny"), scenes), jax.random.PRNGKey(0), scenes)
    p = params["params"]["trunk"]
    np.testing.assert_allclose(jnp.linalg.norm(p["actor"]["kernel"], axis=0), 0.01, rtol=1e-5)
    x = jax.random.normal(jax.random.PRNGKey(1), (4096, p["actor"]["kernel"].shape[0]))
    assert 0.008 < float((x @ p["actor"]["kernel"]).std()) < 0.012
    np.testing.assert_allclose(jnp.linalg.norm(p["critic"]["kernel"], axis=0), 1.0, rtol=1e-5)
    for path, leaf in jax.tree_util.tree_leaves_with_path(params):
        if "bias" in str(path[-1]):
            assert not np.any(np.asarray(leaf)), path
    k = p["global_1x1"]["kernel"]
    bound = np.sqrt(2.0) * np.sqrt(6.0 / sum(k.shape))
    assert float(jnp.abs(k).max()) <= bound and float(jnp.abs(k).max()) > 0.8 * bound


def test_previous_action_input_is_the_previous_steps_probabilities():
    """The carry holds softmax(logits) of the step; zeros start an episode; 'onehot'
    reads the env's one-hot instead."""
    from orgnav_jax.models import previous_action
    from orgnav_jax.models.navmodel import NavModel
    from orgnav_jax.models.encoders import BaselineEncoder
    model = NavModel(BaselineEncoder(), Trunk(glob_channels=F, fuse_channels=F, hidden=H))
    carry = model.initial_carry(2)
    onehot = jax.nn.one_hot(jnp.array([1, 4]), 6)
    np.testing.assert_array_equal(previous_action(model, onehot, carry), 0.0)
    probs = jax.nn.softmax(jnp.arange(12.0).reshape(2, 6))
    carry = NavCarry(carry.lstm, probs)
    np.testing.assert_array_equal(previous_action(model, onehot, carry), probs)
    np.testing.assert_array_equal(previous_action(model.clone(prev_action="onehot"), onehot,
                                                  carry), onehot)


def test_evaluate_cli_runs_a_release_checkpoint_and_refuses_other_widths(tmp_path, tiny_scenes,
                                                                         capsys):
    """`python -m orgnav_jax.evaluate --release-checkpoint F.npz --release-kind K`: a state
    dict of the scenes' feature widths evaluates (as the release: pixel boxes); one of
    other widths, or a missing file, is one line and exit 2 with nothing written."""
    from orgnav_jax import evaluate
    global G, D
    widths = (G, D)
    try:
        G, D = tiny_scenes.global_dim, tiny_scenes.appearance_dim
        good = tmp_path / "graph.npz"
        np.savez(good, **state_dict("GraphModel"))
    finally:
        G, D = widths
    np.savez(tmp_path / "small.npz", **state_dict("BaseModel"))
    out = tmp_path / "r.json"
    result = evaluate.main(["--release-checkpoint", str(good), "--scene-preset", "tiny",
                            "--split", "val", "--episodes-per-room-type", "3", "--quiet",
                            "--out", str(out)])
    assert result["overall"]["episodes"] == 12 and out.exists()
    from orgnav_jax.errors import run_cli
    for path, kind, words in ((tmp_path / "small.npz", "BaseModel", "feature"),
                              (tmp_path / "none.dat", "GraphModel", "none.dat: no such file")):
        bad_out = tmp_path / f"{kind}.json"
        code = run_cli(evaluate.main, ["--release-checkpoint", str(path), "--release-kind", kind,
                                       "--scene-preset", "tiny", "--quiet", "--out",
                                       str(bad_out)])
        err = capsys.readouterr().err
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1, err
        assert not bad_out.exists()


def test_meta_memory_graph_model_loads_its_tpn_head():
    """MetaMemoryGraphModel = GraphModel + the TPN head: every meta_* Linear lands
    transposed in its Dense, every LayerNorm in its scale and bias (the logits' parity with
    the release's module: experiments/parity_tpn.py, docs/tpn.md); a misshapen head entry
    is one line naming it."""
    sd, head = meta_memory_state_dict(5), meta_head_shapes()
    net = release.load("MetaMemoryGraphModel", sd)
    p = net.tpn_params["params"]
    for name, ours in release.RELEASE_TPN.items():
        if len(head[name]) == 2:
            np.testing.assert_array_equal(p[ours]["kernel"], sd[f"{name}.weight"].T)
        else:
            np.testing.assert_array_equal(p[ours]["scale"], sd[f"{name}.weight"])
        np.testing.assert_array_equal(p[ours]["bias"], sd[f"{name}.bias"])
    logits = net.tpn.apply(net.tpn_params, jnp.ones((1, 3, H)), jnp.full((1, 3, 6), 1 / 6),
                           jnp.ones((1, 3), bool))
    assert logits.shape == (1, 3, 6) and np.isfinite(logits).all()
    sd["meta_memory_embedding.3.weight"] = np.zeros((H + 7, 2 * H), np.float32)
    with pytest.raises(release.ReleaseError, match=r"'meta_memory_embedding.3.weight' has "
                                                   r"shape \(23, 32\), expected \(22, 32\)"):
        release.load("MetaMemoryGraphModel", sd)


# ---- issue 55 (bad input, round four): damaged files and widths the model cannot take --

def test_a_damaged_or_misplaced_checkpoint_file_is_one_line_naming_it(tmp_path):
    """A zero-byte or truncated .npz (an interrupted download), a single .npy named .npz
    and a directory: one ReleaseError line naming the file (EOFError, BadZipFile and
    "no such file" before)."""
    whole = tmp_path / "whole.npz"
    np.savez(whole, **state_dict("GraphModel"))
    data = whole.read_bytes()
    (tmp_path / "empty.npz").write_bytes(b"")
    (tmp_path / "cut.npz").write_bytes(data[: len(data) // 2])
    (tmp_path / "head.npz").write_bytes(data[:100])
    with open(tmp_path / "one.npz", "wb") as f:
        np.save(f, np.zeros(3, np.float32))
    (tmp_path / "dir.npz").mkdir()
    for name, words in (("empty.npz", "empty file (0 bytes; an interrupted download?)"),
                        ("cut.npz", "not a readable .npz"),
                        ("head.npz", "not a readable .npz"),
                        ("one.npz", "a single .npy array"),
                        ("dir.npz", "a directory, expected a release checkpoint")):
        with pytest.raises(release.ReleaseError) as err:
            release.read_checkpoint(tmp_path / name)
        assert str(tmp_path / name) in str(err.value) and words in str(err.value), name
        assert "\n" not in str(err.value)
    assert set(release.read_checkpoint(whole)) == set(state_dict("GraphModel"))


def test_an_upper_case_npz_is_an_npz_and_a_zero_width_layer_is_one_line(tmp_path):
    """Issue 67: a release checkpoint named `.NPZ` was read as a torch file; a state dict
    with a zero-width LSTM (or another zero-width layer) ended in a ZeroDivisionError in
    flax's init."""
    upper = tmp_path / "MODEL.NPZ"
    with open(upper, "wb") as f:            # (np.savez would add .npz)
        np.savez(f, **state_dict("GraphModel"))
    assert set(release.read_checkpoint(upper)) == set(state_dict("GraphModel"))
    global H, F
    for name, change, entry, what in (("H", 0, "lstm.weight_hh_l0", r"\(0, 0\): 0 LSTM units"),
                                      ("F", 0, "conv1.weight", r"\(0, 8, 1, 1\): 0 output "
                                                               r"channels")):
        kept = globals()[name]
        try:
            globals()[name] = change
            sd = state_dict("BaseModel")
        finally:
            H, F = (kept, F) if name == "H" else (H, kept)
        with pytest.raises(release.ReleaseError, match=rf"state dict: '{entry}' has shape "
                                                       rf"{what}, expected at least 1"):
            release.load("BaseModel", sd)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf, 1e39])
def test_non_finite_weights_are_refused_naming_the_entry(value):
    """nan / inf (or a float64 beyond float32) evaluated to a constant action at 0%."""
    sd = state_dict("GraphModel")
    sd["lstm.weight_hh_l1"] = sd["lstm.weight_hh_l1"].astype(np.float64)
    sd["lstm.weight_hh_l1"][3, 2] = value
    with pytest.raises(release.ReleaseError, match=r"'lstm.weight_hh_l1' holds 1 non-finite "
                                                   r"value\(s\)") as err:
        release.load("GraphModel", sd)
    assert "\n" not in str(err.value)


def test_widths_the_model_cannot_take_are_one_line_at_load():
    """20 categories (ended in flax's ScopeParamShapeError at the first step) and a critic
    width other than the release's 64 (the same); every mapped shape is compared with the
    model's own (a mismatch there names the state-dict entry)."""
    global C
    try:
        C = 20
        sd = state_dict("GraphModel")
    finally:
        C = 22
    with pytest.raises(release.ReleaseError, match=r"'pointwise.weight' reads 38 channels = "
                                                   r"conv1's 8 \+ 20 category maps .*expected "
                                                   r"22 categories"):
        release.load("GraphModel", sd)
    sd = state_dict("BaseModel")
    sd["critic_linear_1.weight"] = np.ones((32, H), np.float32)
    sd["critic_linear_1.bias"] = np.ones(32, np.float32)
    sd["critic_linear_2.weight"] = np.ones((1, 32), np.float32)
    with pytest.raises(release.ReleaseError, match=r"'critic_linear_1.weight' has shape "
                                                   r"\(32, 16\), expected \(64, 16\)"):
        release.load("BaseModel", sd)
    net = release.load("GraphModel", state_dict("GraphModel"))
    tree = jax.tree_util.tree_map(np.asarray, net.params["params"])
    tree["encoder"]["relation_3"]["kernel"] = np.zeros((C, C + 1), np.float32)
    with pytest.raises(release.ReleaseError, match=r"'graph_detection_other_info_linear_3' "
                                                   r"gives encoder/relation_3/kernel the shape "
                                                   r"\(22, 23\), expected \(22, 22\)"):
        release._check_model_shapes("GraphModel", net.model, tree, G, D)


def meta_head_shapes() -> dict:
    """The MetaMemoryGraphModel's TPN head entries (without .weight/.bias) -> weight shape."""
    Hm = 2 * H + 6
    return {"meta_current_state_embedding.0": (H // 2, H), "meta_current_state_embedding.1": (H // 2,),
            "meta_current_state_embedding.3": (H, H // 2), "meta_current_state_embedding.4": (H,),
            "meta_current_action_embedding": (6, 6),
            "meta_memory_embedding.0": (2 * H, H + 6), "meta_memory_embedding.1": (2 * H,),
            "meta_memory_embedding.3": (H + 6, 2 * H), "meta_memory_embedding.4": (H + 6,),
            "meta_learning_residual_block.0": (H, Hm), "meta_learning_residual_block.1": (H,),
            "meta_learning_residual_block.3": (Hm, H), "meta_learning_residual_block.4": (Hm,),
            "meta_learning_predict.0": (H, Hm), "meta_learning_predict.2": (6, H)}


def meta_memory_state_dict(seed: int = 5) -> dict:
    """A GraphModel state dict with the MetaMemoryGraphModel's TPN head (random)."""
    sd = state_dict("GraphModel")
    rng = np.random.default_rng(seed)
    for name, shape in meta_head_shapes().items():
        sd[f"{name}.weight"] = rng.standard_normal(shape).astype(np.float32)
        sd[f"{name}.bias"] = rng.standard_normal(shape[:1]).astype(np.float32)
    return sd


def test_meta_memory_graph_model_evaluates_with_its_tpn_head(tmp_path, tiny_scenes, cli_error):
    """--release-kind MetaMemoryGraphModel evaluated the navigation network and dropped the
    TPN head it loaded, under the MetaMemory label: now its policy is the test-time TPN
    policy on the loaded head (the release's settings; the test-time options apply), and
    with --tpn-lr 0 its episodes are the GraphModel's own. Test-time options with another
    kind are refused."""
    from orgnav_jax import api, evaluate
    global G, D
    widths = (G, D)
    try:
        G, D = tiny_scenes.global_dim, tiny_scenes.appearance_dim
        sd = meta_memory_state_dict()
        np.savez(tmp_path / "mm.npz", **sd)
        np.savez(tmp_path / "graph.npz", **{k: v for k, v in sd.items()
                                            if not k.startswith("meta_")})
    finally:
        G, D = widths
    loaded = api.load_policy(release_checkpoint=str(tmp_path / "mm.npz"),
                             release_kind="MetaMemoryGraphModel")
    assert loaded.policy.name == "MetaMemoryGraphModel+TPN" and loaded.name == \
        "mm-MetaMemoryGraphModel+TPN"
    np.testing.assert_array_equal(loaded.params["tpn"]["params"]["predict_2"]["kernel"],
                                  sd["meta_learning_predict.2.weight"].T)
    common = ["--scene-preset", "tiny", "--split", "val", "--episodes-per-room-type", "1",
              "--quiet"]
    mm = evaluate.main(["--release-checkpoint", str(tmp_path / "mm.npz"), "--release-kind",
                        "MetaMemoryGraphModel", "--tpn-lr", "0", "--out",
                        str(tmp_path / "mm.json"), *common])
    graph = evaluate.main(["--release-checkpoint", str(tmp_path / "graph.npz"), "--out",
                           str(tmp_path / "graph.json"), *common])
    assert mm["policy"] == "mm-MetaMemoryGraphModel+TPN"
    assert mm["per_episode"] == graph["per_episode"]
    line = cli_error(evaluate.main, ["--release-checkpoint", tmp_path / "graph.npz",
                                     "--tpn-lr", "1e-3", "--out", tmp_path / "x.json", *common])
    assert "need --tpn TPN_RUN_DIR or --release-kind MetaMemoryGraphModel" in line
    line = cli_error(evaluate.main, ["--release-checkpoint", tmp_path / "mm.npz",
                                     "--release-kind", "MetaMemoryGraphModel", "--tpn-lr", "-1",
                                     "--out", tmp_path / "x.json", *common])
    assert "'tpn_lr': -1.0" in line and not (tmp_path / "x.json").exists()
