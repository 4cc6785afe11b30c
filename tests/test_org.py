"""ORG / released ORG / D-SP encoders (the paper's, and the replace form of config versions
<= 6), the adjacency picture, and trial-driven IL masks."""

from __future__ import annotations

import functools
import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from orgnav_jax import constants as K
from orgnav_jax import env
from orgnav_jax.models import ModelInputs, build_model, init_params
from orgnav_jax.models.org import (
    DSPEncoder, DSPReplaceEncoder, ORGEncoder, ReleasedORGEncoder, as_static_matrix,
    cooccurrence_adjacency)
from orgnav_jax.plots import anchor_pair_report, find_adjacency, plot_adjacency
from orgnav_jax.training.config import get_config
from orgnav_jax.training.losses import il_mask, imitation_loss

C, D, B = K.NUM_CATEGORIES, 8, 3


def _inputs(seed, batch=B, d=D):
    """Random detections (numpy: no per-op compiles) -> (app, box, conf, target)."""
    rng = np.random.default_rng(seed)
    conf = (rng.random((batch, C)) * (rng.random((batch, C)) > 0.4)).astype(np.float32)
    det = (conf > 0)[..., None]
    app = (np.maximum(rng.standard_normal((batch, C, d)), 0) * det).astype(np.float32)
    box = (rng.random((batch, C, 4)) * det).astype(np.float32)
    target = np.eye(C, dtype=np.float32)[np.arange(batch) % C]
    return app, box, conf, target


def _fake_scenes(n=6, d=D, g=5):
    rng = np.random.default_rng(0)
    return SimpleNamespace(present=rng.random((n, C)) < 0.5, appearance_dim=d, global_dim=g)


ENCODER_MODULES = {
    "org": ORGEncoder(),
    "org_released": ReleasedORGEncoder(),
    "dsp_replace": DSPReplaceEncoder(
        as_static_matrix(cooccurrence_adjacency(_fake_scenes().present))),
}


@functools.cache
def _compiled(name):
    """(jitted init, jitted apply) of ENCODER_MODULES[name], shared by the tests."""
    enc = ENCODER_MODULES[name]
    return jax.jit(enc.init), jax.jit(enc.apply)


def _init(name, seed=1):
    return _compiled(name)[0](jax.random.PRNGKey(seed), *_inputs(0))


@pytest.mark.parametrize("name", sorted(ENCODER_MODULES))
def test_encoder_output_shape(name):
    out = _compiled(name)[1](_init(name), *_inputs(0))
    assert out.shape == (B, C, 49) and np.isfinite(np.asarray(out)).all()


@pytest.mark.parametrize("name", ["org", "org_released", "dsp", "dsp_replace"])
def test_navmodel_with_each_encoder(name):
    """build_model / init_params / apply with each encoder (shapes only: traced, not run)."""
    scenes = _fake_scenes()
    model = build_model(get_config("tiny", model=name), scenes)
    params = jax.eval_shape(lambda k: init_params(model, k, scenes), jax.random.PRNGKey(0))
    app, box, conf, target = _inputs(2, batch=2)
    inputs = ModelInputs(np.ones((2, 7, 7, scenes.global_dim), np.float32), app, box, conf,
                         target, np.eye(K.NUM_ACTIONS, dtype=np.float32)[[0, 3]])
    carry0 = model.initial_carry(2)
    logits, value, _, h = jax.eval_shape(model.apply, params, inputs, carry0)
    assert logits.shape == (2, K.NUM_ACTIONS) and value.shape == (2,)
    assert h.shape == (2, get_config("tiny").hidden)
    enc = params["params"]["encoder"]
    assert ("adjacency" in enc) == (name == "org")
    if name == "org":
        assert enc["adjacency"].shape == (C, C)


def test_org_permutation_equivariance():
    """Relabelling the categories by P (inputs, A -> P A P^T, W's category columns ->
    W P^T) permutes the output rows."""
    params = _init("org")
    params["params"]["adjacency"] = jnp.asarray(
        np.eye(C) + 0.3 * np.random.default_rng(4).standard_normal((C, C)), jnp.float32)
    x = _inputs(3)
    perm = np.random.default_rng(1).permutation(C)
    p = jax.tree_util.tree_map(lambda a: a, params)
    p["params"]["adjacency"] = params["params"]["adjacency"][perm][:, perm]
    p["params"]["embed_W"]["kernel"] = params["params"]["embed_W"]["kernel"][:, perm]
    apply = _compiled("org")[1]
    out = apply(params, *x)
    out_p = apply(p, *(a[:, perm] for a in x))
    np.testing.assert_allclose(np.asarray(out_p), np.asarray(out)[:, perm],
                               rtol=1e-5, atol=1e-5)
    # and A matters: a different (unpermuted) A changes the output
    q = jax.tree_util.tree_map(lambda a: a, params)
    q["params"]["adjacency"] = params["params"]["adjacency"][perm]
    assert not np.allclose(np.asarray(apply(q, *x)), np.asarray(out), atol=1e-5)


def test_dsp_replace_permutation_equivariance():
    """Permuting the inputs and the prior graph (P A P^T) permutes the output rows of the
    replace form of D-SP (model dsp_replace)."""
    A = cooccurrence_adjacency(_fake_scenes().present)
    perm = np.random.default_rng(2).permutation(C)
    x = _inputs(5)
    params = _init("dsp_replace")
    enc_p = DSPReplaceEncoder(as_static_matrix(A[perm][:, perm]))
    out_p = jax.jit(enc_p.apply)(params, *(a[:, perm] for a in x))
    out = _compiled("dsp_replace")[1](params, *x)
    np.testing.assert_allclose(np.asarray(out_p), np.asarray(out)[:, perm],
                               rtol=1e-5, atol=1e-5)


def _dsp_and_baseline():
    """(D-SP model, Baseline model, D-SP parameters, inputs, carry) at the tiny widths."""
    scenes = _fake_scenes()
    dsp = build_model(get_config("tiny", model="dsp"), scenes)
    base = build_model(get_config("tiny", model="baseline"), scenes)
    params = init_params(dsp, jax.random.PRNGKey(5), scenes)
    # the last graph layer's inputs are >= 0 (ReLUs of >= 0 detection features): with a
    # kernel >= 0 every node's value is alive (at init some draws leave it all at 0,
    # docs/training.md)
    g2 = params["params"]["encoder"]["graph_2"]
    g2["kernel"] = jnp.abs(g2["kernel"])
    app, box, conf, target = _inputs(6, batch=4)
    inputs = ModelInputs(np.random.default_rng(7).standard_normal(
        (4, 7, 7, scenes.global_dim)).astype(np.float32), app, box, conf, target,
        np.full((4, K.NUM_ACTIONS), 1 / K.NUM_ACTIONS, np.float32))
    carry = jax.tree_util.tree_map(lambda z: z + 0.1, dsp.initial_carry(4))
    return dsp, base, params, inputs, carry


def test_dsp_is_the_baseline_plus_a_graph_branch():
    """D-SP as SAVN's release builds Scene Priors (models/gcn.py): with the graph branch's
    output zeroed it computes the Baseline's function of the same parameters (the LSTM
    input kernel's rows for the branch dropped), and the target's own detection reaches
    the LSTM unblurred (its map is the Baseline's map of its own features only)."""
    dsp, base, params, inputs, carry = _dsp_and_baseline()
    enc = params["params"]["encoder"]
    assert sorted(enc) == ["graph_0", "graph_1", "graph_2", "graph_out", "to_map"]
    d6 = D + 6
    assert [enc[f"graph_{i}"]["kernel"].shape for i in range(3)] == [(d6, d6), (d6, d6),
                                                                     (d6, 1)]
    hidden = get_config("tiny").hidden
    assert enc["graph_out"]["kernel"].shape == (C, hidden)
    kernel = params["params"]["trunk"]["lstm_0"]["input_kernel"]
    flat = 49 * get_config("tiny").fuse_channels
    assert kernel.shape[0] == flat + hidden            # the LSTM input grows by the branch
    zeroed = jax.tree_util.tree_map(lambda x: x, params)
    zeroed["params"]["encoder"]["graph_out"] = jax.tree_util.tree_map(
        jnp.zeros_like, enc["graph_out"])
    base_params = jax.tree_util.tree_map(lambda x: x, params)
    base_params["params"]["encoder"] = {"to_map": enc["to_map"]}
    base_params["params"]["trunk"]["lstm_0"] = dict(
        params["params"]["trunk"]["lstm_0"], input_kernel=kernel[:flat])
    out_dsp = jax.jit(dsp.apply)(zeroed, inputs, carry)
    out_base = jax.jit(base.apply)(base_params, inputs, carry)
    for a, b in zip(jax.tree_util.tree_leaves(out_dsp), jax.tree_util.tree_leaves(out_base)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)
    # and the branch matters when it is not zeroed
    h_full = np.asarray(jax.jit(dsp.apply)(params, inputs, carry)[3])
    assert np.abs(h_full - np.asarray(out_dsp[3])).max() > 1e-3
    # the target's map depends on its own detection only; its neighbours reach the LSTM
    # through the graph vector, not through the target's map
    maps = jax.jit(lambda p, *x: dsp.apply(p, *x, method=lambda m, *a: m.encoder(*a)))
    x = (inputs.app, inputs.box, inputs.conf, inputs.target)
    t = np.argmax(np.asarray(inputs.target), -1)
    other = (t + 1) % C
    app2 = np.asarray(inputs.app).copy()
    app2[np.arange(4), other] += 1.0
    (m1, e1), (m2, e2) = maps(params, *x), maps(params, app2, *x[1:])
    rows = np.arange(4)
    np.testing.assert_array_equal(np.asarray(m1)[rows, t], np.asarray(m2)[rows, t])
    assert not np.allclose(np.asarray(e1), np.asarray(e2))


def test_old_dsp_runs_load_as_the_replace_form(tmp_path):
    """A run saved with config version <= 6 and model "dsp" trained the replace form: it
    loads as model dsp_replace (and evaluates as trained); a version-7 "dsp" stays dsp."""
    import json
    from orgnav_jax.training.config import CONFIG_VERSION, load_config
    doc = json.loads(get_config("tiny", model="dsp").to_json())
    for version, want in ((6, "dsp_replace"), (CONFIG_VERSION, "dsp")):
        run = tmp_path / f"v{version}"
        run.mkdir()
        d = dict(doc, version=version)
        if version == 6:      # a version-6 config lacks the fields added since
            from orgnav_jax.training.config import V7_DEFAULTS
            d = {k: v for k, v in d.items() if k not in V7_DEFAULTS}
        (run / "config.json").write_text(json.dumps(d))
        assert load_config(run).model == want


def test_gradients_reach_the_adjacency():
    enc, x = ENCODER_MODULES["org"], _inputs(7)
    params = _init("org")

    def loss(p):
        return (enc.apply(p, *x) ** 2).mean()

    grads = jax.jit(jax.grad(loss))(params)
    g = find_adjacency({"params": {"encoder": grads["params"]}})    # as inside a NavModel
    assert g.shape == (C, C) and np.isfinite(g).all()
    assert np.abs(g).max() > 0
    assert np.count_nonzero(g - np.diag(np.diag(g))) > 0   # off-diagonal entries too


def test_cooccurrence_adjacency_from_hand_made_presence():
    present = np.zeros((4, C), bool)
    present[:, [0, 1]] = True        # 0 and 1 always together
    present[:2, 2] = True            # 2 with them in half the rooms
    present[2:, 3] = True            # 3 never with 2
    A = cooccurrence_adjacency(present)
    assert A.shape == (C, C) and A.dtype == np.float32
    np.testing.assert_allclose(A, A.T)
    assert (A >= 0).all()
    assert A[2, 3] == 0 and A[0, 3] > 0
    assert A[0, 1] > A[0, 2] > 0     # always together > sometimes together
    assert (A[4:, :4] == 0).all()    # absent categories: only their self-loop
    np.testing.assert_allclose(np.diag(A)[4:], 1.0)
    # the un-normalised graph before D^-1/2 (A + I) D^-1/2: recover it
    d = 1.0 / np.diag(A)             # diag(A_hat) = 1 / D_ii
    raw = A * np.sqrt(np.outer(d, d)) - np.eye(C)
    np.testing.assert_allclose(raw[0, 1], 1.0, atol=1e-6)
    np.testing.assert_allclose(raw[0, 2], 2 / math.sqrt(4 * 2), atol=1e-6)


def test_il_mask_is_the_deadlock_steps_of_an_episode(tiny_scenes):
    """A hand-chosen episode: a failed MoveAhead, then rotations back into visited states."""
    train = tiny_scenes.split_view("train").to_device()
    params = env.EnvParams()
    n = 0
    nxt = np.asarray(train.next_state)
    rows = train.state_slice(n)
    start = int(np.flatnonzero(nxt[rows, K.MOVE_AHEAD] == np.arange(rows.start, rows.stop))[0])
    target = int(np.flatnonzero(np.asarray(train.targets[n]))[0])
    st = env.start_episode(jnp.int32(n), jnp.int32(start), jnp.int32(target), train, params)
    obs = env.observe(st, train)
    actions = [K.MOVE_AHEAD, K.ROTATE_LEFT, K.ROTATE_RIGHT, K.ROTATE_RIGHT, K.ROTATE_LEFT]
    deadlock, failed, states = [obs.deadlock], [st.last_failed], [int(st.state)]
    step = jax.jit(env.step_env, static_argnums=3)
    for a in actions:
        obs, st, _, done, _ = step(st, jnp.int32(a), train, params)
        assert not bool(done)
        deadlock.append(obs.deadlock)
        failed.append(st.last_failed)
        states.append(int(st.state))
    # obs t: 0 start, 1 after the failed move, 2 new heading, 3 back at start,
    # 4 the other heading (new), 5 back at start again
    expected = np.array([0, 1, 0, 1, 0, 1], float)
    # independent check: a step is a deadlock iff its state was visited before
    np.testing.assert_array_equal(expected, [s in states[:t] for t, s in enumerate(states)])
    traj = SimpleNamespace(action=jnp.zeros((len(states), 1), jnp.int32),
                           obs=SimpleNamespace(deadlock=jnp.stack(deadlock)[:, None]),
                           last_failed=jnp.stack(failed)[:, None])     # (T, N=1)
    np.testing.assert_array_equal(
        np.asarray(il_mask("deadlock", "state", traj))[:, 0], expected)
    np.testing.assert_array_equal(
        np.asarray(il_mask("failed", "state", traj))[:, 0], [0, 1, 0, 0, 0, 0])


def test_imitation_loss_equals_hand_computed_value():
    logits = jnp.array([[[0.0] * 6, [2.0, 0, 0, 0, 0, 0]],
                        [[1.0, 1, 1, 1, 1, math.log(2)], [5.0, 0, 0, 0, 0, 0]]])
    expert = jnp.array([[3, 0], [5, -1]])            # -1 = no expert action: never counted
    mask = jnp.array([[1.0, 1.0], [1.0, 1.0]])
    loss, steps = imitation_loss(logits, expert, mask)
    ce = [math.log(6),                                # uniform over 6 actions
          math.log(1 + 5 * math.exp(-2)),             # -log(e^2 / (e^2 + 5))
          -math.log(2 / (5 * math.e + 2))]            # -log(e^log2 / (5e + 2))
    assert float(steps) == 3
    assert float(loss) == pytest.approx(sum(ce) / 3, rel=1e-6)
    loss1, steps1 = imitation_loss(logits, expert, jnp.array([[0.0, 1.0], [0.0, 0.0]]))
    assert float(steps1) == 1 and float(loss1) == pytest.approx(ce[1], rel=1e-6)
    loss0, steps0 = imitation_loss(logits, expert, jnp.zeros((2, 2)))
    assert float(loss0) == 0.0 and float(steps0) == 0


def test_plot_adjacency_writes_png(tmp_path):
    A = np.eye(C) + 0.05 * np.random.default_rng(0).standard_normal((C, C))
    path = plot_adjacency(A, tmp_path / "a" / "adj.png", "test")
    assert path.exists() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_anchor_pair_report():
    A = np.zeros((C, C))
    i, j = K.CATEGORY_INDEX["RemoteControl"], K.CATEGORY_INDEX["Television"]
    A[i, j] = A[j, i] = 1.0
    rep = anchor_pair_report(A)
    by = {p["pair"]: p for p in rep["pairs"]}
    rt = by["RemoteControl-Television"]
    assert rt["higher"] and rt["kind"] == "anchor"
    assert by["CoffeeMachine-Toaster"]["kind"] == "sibling"
    assert not by["CoffeeMachine-Toaster"]["higher"] and not rep["reflects"]
    rep2 = anchor_pair_report(A + cooccurrence_anchor_matrix())
    assert rep2["reflects"] and rep2["anchor"]["higher"] == rep2["anchor"]["n"]
    assert rep2["anchor"]["p_value"] < 1e-3 and rep2["sibling"]["p_value"] > 0.05
    noise = np.random.default_rng(3).standard_normal((C, C))
    assert not anchor_pair_report(noise)["reflects"]
    # AUC of anchor pairs against the other same-room-type pairs
    assert rep2["anchor_auc"] == 1.0
    n = rep["anchor"]["n"]
    assert rep["anchor_auc"] == pytest.approx((1 + 0.5 * (n - 1)) / n)
    assert abs(anchor_pair_report(noise)["anchor_auc"] - 0.5) < 0.25


def test_adjacency_json_has_the_report_keys(tmp_path, monkeypatch, capsys):
    import json

    from orgnav_jax import plots
    A = np.eye(C) + cooccurrence_anchor_matrix()
    monkeypatch.setattr(plots.adjacency, "run_adjacency", lambda run_dir, best=True: (A, "org"))
    run = tmp_path / "org-s0"
    run.mkdir()
    assert plots.main(["adjacency", str(run), "--json"]) == 0
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert {"anchor", "sibling", "anchor_auc", "pairs", "reflects", "run_dir"} <= set(report)
    assert {"p_value", "n", "higher", "mean"} <= set(report["anchor"])
    assert report["anchor_auc"] == 1.0 and f"wrote {run / 'adjacency.png'}" in err


def cooccurrence_anchor_matrix():
    """1 on every (object, anchor) pair of the generator's rules."""
    from orgnav_jax.scenes.synthetic.catalog import ANCHORS
    M = np.zeros((C, C))
    for o, anchors in ANCHORS.items():
        for a in anchors:
            i, j = K.CATEGORY_INDEX[o], K.CATEGORY_INDEX[a]
            M[i, j] = M[j, i] = 1
    return M


def test_init_params_is_one_program_per_model_and_equals_the_op_by_op_init():
    """init_params is jitted with the model as a static argument: every model kind is
    hashable and equal when rebuilt, so a rebuilt model reuses the program; its parameters
    are the bits flax's op-by-op init followed by the release's initialisation give."""
    from orgnav_jax.models import navmodel
    scenes = _fake_scenes()
    for name in sorted(navmodel.ENCODERS):
        cfg = get_config("tiny", model=name)
        assert build_model(cfg, scenes) == build_model(cfg, scenes), name
        assert hash(build_model(cfg, scenes)) == hash(build_model(cfg, scenes)), name
    model = build_model(get_config("tiny", model="dsp"), scenes)
    key = jax.random.PRNGKey(3)
    jitted = init_params(model, key, scenes)
    size = navmodel._init_params._cache_size()
    again = init_params(build_model(get_config("tiny", model="dsp"), scenes), key, scenes)
    assert navmodel._init_params._cache_size() == size
    inputs = navmodel.dummy_inputs(scenes.present.shape[-1], scenes.global_dim,
                                   scenes.appearance_dim)
    from orgnav_jax.models.init import release_init
    eager = jax.jit(release_init)(model.init({"params": key}, inputs, model.initial_carry(1)),
                                  jax.random.fold_in(key, 1))
    flat = lambda t: jax.tree_util.tree_leaves_with_path(t)
    assert [p for p, _ in flat(jitted)] == [p for p, _ in flat(eager)]
    for (path, x), (_, y), (_, z) in zip(flat(jitted), flat(eager), flat(again)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=str(path))
        np.testing.assert_array_equal(np.asarray(x), np.asarray(z), err_msg=str(path))
