"""The authors' released weights in: their PyTorch state dicts as orgnav_jax models.

    from orgnav_jax.models import release
    net = release.load("GraphModel", state_dict)      # {torch name: numpy array}
    logits, value, (h, c) = net.step(state, appear, info, indicator, action_probs, (h, c))
    sd = release.read_checkpoint("model.dat")          # needs torch: orgnav_jax[release]

kind: "BaseModel" (our `baseline`), "GraphModel" (our `org_released`) or
"MetaMemoryGraphModel" (GraphModel + the TPN head: `net.tpn`, `net.tpn_params`), of
xiaobaishu0097/ECCV-VN `models/`. Widths (global map channels, appearance width,
hidden size, LSTM layers) are read from the shapes, so a state dict of other widths
loads too; the categories must be the 22 and the critic width the release's 64 (the
model is built for those). `step` takes the release's layouts, batch first: state
(B, G, 7, 7), appear (B, C, d), info (B, C, 5) = box (x1, y1, x2, y2, as given: the
release feeds the detection file's pixel values, where our scenes' inputs are boxes / 300)
and confidence, indicator (B, C, 1), action_probs (B, 6) (zeros at an episode start),
h and c (layers, B, H) -> logits (B, 6), value (B, 1), (h, c) (layers, B, H): the release's
forward in eval mode (no dropout). `tools/parity/` of the project's shared folder checks
it against the release's own classes. The core needs numpy only; torch only to read a
`.dat` file.

What `load` refuses (ReleaseError, one line naming the entry): a missing, extra or
misshapen entry; a non-finite weight (nan, inf, or a float64 beyond float32: a damaged
file would otherwise evaluate to a constant action); widths the model cannot be built
with (categories other than the 22 every scene set has, a critic width other than the
release's 64): every inferred width is checked against the parameter shapes of the
model it builds, before anything runs. `read_checkpoint` refuses a directory, an empty
or truncated file (an interrupted download), naming the file.

Mapping: a torch Linear weight (out, in) is a Dense kernel (in, out); a 1x1 Conv weight
(out, in, 1, 1) likewise; the LSTM's gates (i, f, g, o) are in the same order, its two
biases are summed, and the first layer's input rows are permuted from torch's
channel-major flattening of the 7x7x64 map (c * 49 + cell) to ours (cell * 64 + c).
"""

from __future__ import annotations

import dataclasses
import os
import zipfile
import zlib
from functools import partial
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS, NUM_CATEGORIES
from orgnav_jax.models.encoders import BaselineEncoder
from orgnav_jax.models.navmodel import ModelInputs, NavCarry, NavModel, dummy_inputs
from orgnav_jax.models.org import ReleasedORGEncoder
from orgnav_jax.models.tpn_net import TPN
from orgnav_jax.models.trunk import Trunk

KINDS = ("BaseModel", "GraphModel", "MetaMemoryGraphModel")
ORG_LAYERS = 5            # graph_detection_other_info_linear_1 .. _5
CELLS = FEATURE_GRID * FEATURE_GRID
CRITIC_HIDDEN = 64        # critic_linear_1's width: the release's, and Trunk.critic_hidden's
RELEASE_DROPOUT = 0.25    # the release's dropout_rate (its "+TPN" runs in train mode)
# MetaMemoryGraphModel's TPN head: torch module -> our TPN's (models/tpn_net.py)
RELEASE_TPN = {
    "meta_current_state_embedding.0": "rep_1", "meta_current_state_embedding.1": "rep_norm_1",
    "meta_current_state_embedding.3": "rep_2", "meta_current_state_embedding.4": "rep_norm_2",
    "meta_current_action_embedding": "prob_embed",
    "meta_memory_embedding.0": "memory_1", "meta_memory_embedding.1": "memory_norm_1",
    "meta_memory_embedding.3": "memory_2", "meta_memory_embedding.4": "memory_norm_2",
    "meta_learning_residual_block.0": "block_1", "meta_learning_residual_block.1": "block_norm_1",
    "meta_learning_residual_block.3": "block_2", "meta_learning_residual_block.4": "block_norm_2",
    "meta_learning_predict.0": "predict_1", "meta_learning_predict.2": "predict_2",
}


class ReleaseError(ValueError):
    """A state dict that is not one of the release's models (one line, naming the entry)."""


def _get(sd: dict, name: str, ndim: int) -> np.ndarray:
    if name not in sd:
        raise ReleaseError(f"state dict: missing parameter {name!r}")
    x = np.asarray(sd[name])
    if x.ndim != ndim or not np.issubdtype(x.dtype, np.floating):
        raise ReleaseError(f"state dict: {name!r} has shape {x.shape} ({x.dtype}), expected "
                           f"a {ndim}-d float array")
    return x.astype(np.float32)


def _expect(name: str, x: np.ndarray, shape: tuple) -> None:
    if x.shape != tuple(shape):
        raise ReleaseError(f"state dict: {name!r} has shape {x.shape}, expected {tuple(shape)}")


def _dense(sd: dict, name: str, n_in: int | None = None, n_out: int | None = None) -> dict:
    """torch Linear `name` -> {"kernel" (in, out), "bias" (out,)}, shapes checked."""
    w = _get(sd, f"{name}.weight", 2)
    out, inp = w.shape
    _expect(f"{name}.weight", w, (n_out or out, n_in or inp))
    b = _get(sd, f"{name}.bias", 1)
    _expect(f"{name}.bias", b, (out,))
    return {"kernel": w.T, "bias": b}


def _conv1x1(sd: dict, name: str) -> dict:
    """torch 1x1 Conv2d `name` -> {"kernel" (in, out), "bias" (out,)}."""
    w = _get(sd, f"{name}.weight", 4)
    if w.shape[2:] != (1, 1):
        raise ReleaseError(f"state dict: {name + '.weight'!r} has shape {w.shape}, expected "
                           "a 1x1 convolution (out, in, 1, 1)")
    return _dense({**sd, f"{name}.weight": w[:, :, 0, 0]}, name)


def _lstm(sd: dict, layers: int, n_in: int, hidden: int, fuse: int) -> dict:
    """torch nn.LSTM -> {"lstm_i": {input_kernel, recurrent_kernel, bias}}."""
    out = {}
    for i in range(layers):
        w_ih = _get(sd, f"lstm.weight_ih_l{i}", 2)
        w_hh = _get(sd, f"lstm.weight_hh_l{i}", 2)
        _expect(f"lstm.weight_ih_l{i}", w_ih, (4 * hidden, n_in if i == 0 else hidden))
        _expect(f"lstm.weight_hh_l{i}", w_hh, (4 * hidden, hidden))
        bias = 0
        for b in ("ih", "hh"):
            x = _get(sd, f"lstm.bias_{b}_l{i}", 1)
            _expect(f"lstm.bias_{b}_l{i}", x, (4 * hidden,))
            bias = bias + x
        kernel = w_ih.T
        if i == 0:      # rows: torch's c * 49 + cell -> ours cell * fuse + c
            cell, c = np.divmod(np.arange(n_in), fuse)
            kernel = kernel[c * CELLS + cell]
        out[f"lstm_{i}"] = {"input_kernel": kernel, "recurrent_kernel": w_hh.T, "bias": bias}
    return out


def _expected_names(kind: str, layers: int) -> set[str]:
    linear = ["embed_action", "critic_linear_1", "critic_linear_2", "actor_linear"]
    if kind == "BaseModel":
        linear.append("detection_feature")
    else:
        linear += ["graph_detection_feature.0", "graph_detection_feature.2"]
        linear += [f"graph_detection_other_info_linear_{i}" for i in range(1, ORG_LAYERS + 1)]
    if kind == "MetaMemoryGraphModel":
        linear += list(RELEASE_TPN)          # its LayerNorms have a weight and a bias too
    names = {f"{n}.{p}" for n in linear + ["conv1", "pointwise"] for p in ("weight", "bias")}
    names |= {f"lstm.{p}_{g}_l{i}" for i in range(layers) for p in ("weight", "bias")
              for g in ("ih", "hh")}
    return names


def _count_layers(sd: dict) -> int:
    layers = 0
    while f"lstm.weight_ih_l{layers}" in sd:
        layers += 1
    if layers == 0:
        raise ReleaseError("state dict: missing parameter 'lstm.weight_ih_l0'")
    return layers


@dataclasses.dataclass(frozen=True)
class ReleaseNet:
    """A release model as an orgnav_jax NavModel with its parameters (see module
    docstring); tpn / tpn_params: the TPN head of a MetaMemoryGraphModel, else None."""
    kind: str
    model: NavModel
    params: Any
    tpn: Any = None
    tpn_params: Any = None

    def step(self, state, appear, info, indicator, action_probs, hidden):
        """One step in the release's layouts (module docstring) -> (logits (B, 6),
        value (B, 1), (h, c) each (layers, B, H))."""
        h, c = (jnp.asarray(x, jnp.float32) for x in hidden)
        logits, value, (h, c) = _step(self.model, self.params, jnp.asarray(state),
                                      jnp.asarray(appear), jnp.asarray(info),
                                      jnp.asarray(indicator), jnp.asarray(action_probs), h, c)
        return np.asarray(logits), np.asarray(value), (np.asarray(h), np.asarray(c))


@partial(jax.jit, static_argnums=0)
def _step(model, params, state, appear, info, indicator, probs, h, c):
    inputs = ModelInputs(glob=jnp.transpose(state, (0, 2, 3, 1)), app=appear,
                         box=info[..., :4], conf=info[..., 4], target=indicator[..., 0],
                         prev_action=probs)
    carry = NavCarry(tuple((c[i], h[i]) for i in range(h.shape[0])), probs)
    gates = model.apply(params, inputs, method=model.embed)
    logits, value, carry, _ = model.apply(params, gates, carry, method=model.recur)
    h = jnp.stack([hh for _, hh in carry.lstm])
    c = jnp.stack([cc for cc, _ in carry.lstm])
    return logits, value[:, None], (h, c)


def load(kind: str, state_dict: dict) -> ReleaseNet:
    """The release's `kind` from its state dict {torch name: array} -> ReleaseNet.
    ReleaseError (one line) for an unknown kind or a missing, extra or misshapen entry."""
    if kind not in KINDS:
        raise ReleaseError(f"release kind {kind!r}: expected one of {list(KINDS)}")
    if not isinstance(state_dict, dict):
        raise ReleaseError(f"state dict: expected a dict of arrays, got "
                           f"{type(state_dict).__name__}")
    sd = state_dict
    layers = _count_layers(sd)
    extra = sorted(set(sd) - _expected_names(kind, layers))
    if extra:
        raise ReleaseError(f"state dict: unexpected parameter {extra[0]!r} for a {kind}"
                           + (f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""))
    _check_finite(sd)
    conv1 = _conv1x1(sd, "conv1")
    G, glob = conv1["kernel"].shape
    action = _dense(sd, "embed_action", n_in=NUM_ACTIONS)
    pointwise = _conv1x1(sd, "pointwise")
    in_ch, fuse = pointwise["kernel"].shape
    C = in_ch - glob - action["kernel"].shape[1]
    if C <= 0:
        raise ReleaseError(f"state dict: 'pointwise.weight' has {in_ch} input channels, "
                           f"expected conv1's {glob} + categories + embed_action's "
                           f"{action['kernel'].shape[1]}")
    if C != NUM_CATEGORIES:
        raise ReleaseError(f"state dict: 'pointwise.weight' reads {in_ch} channels = conv1's "
                           f"{glob} + {C} category maps + embed_action's "
                           f"{action['kernel'].shape[1]}: expected {NUM_CATEGORIES} "
                           "categories (the release's, and every scene set's)")
    H = _get(sd, "lstm.weight_hh_l0", 2).shape[1]
    for name, n, what in (("conv1.weight", G, "input channels (the scenes' global_dim)"),
                          ("conv1.weight", glob, "output channels"),
                          ("embed_action.weight", action["kernel"].shape[1], "outputs"),
                          ("pointwise.weight", fuse, "output channels"),
                          ("lstm.weight_hh_l0", H, "LSTM units")):
        _nonzero(sd, name, n, what)     # (a zero width divided by zero in flax's init)
    critic_1 = _dense(sd, "critic_linear_1", n_in=H, n_out=CRITIC_HIDDEN)
    trunk_params = {
        "global_1x1": conv1, "action_dense": action, "fuse_1x1": pointwise,
        **_lstm(sd, layers, CELLS * fuse, H, fuse),
        "actor": _dense(sd, "actor_linear", n_in=H, n_out=NUM_ACTIONS),
        "critic_hidden": critic_1,
        "critic": _dense(sd, "critic_linear_2", n_in=critic_1["kernel"].shape[1], n_out=1)}
    if kind == "BaseModel":
        to_map = _dense(sd, "detection_feature", n_out=CELLS)
        d = to_map["kernel"].shape[0] - 6
        encoder = BaselineEncoder()
        enc_params = {"to_map": to_map}
    else:
        hidden = _dense(sd, "graph_detection_feature.0")
        _nonzero(sd, "graph_detection_feature.0.weight", hidden["kernel"].shape[1], "outputs")
        d = hidden["kernel"].shape[0] - 6
        enc_params = {"hidden": hidden, "to_map": _dense(
            sd, "graph_detection_feature.2", n_in=hidden["kernel"].shape[1], n_out=CELLS)}
        for i in range(1, ORG_LAYERS + 1):
            enc_params[f"relation_{i}"] = _dense(sd, f"graph_detection_other_info_linear_{i}",
                                                 n_in=6 if i == 1 else C, n_out=C)
        encoder = ReleasedORGEncoder(hidden=hidden["kernel"].shape[1], wiring="release")
    if d <= 0:
        raise ReleaseError(f"state dict: the detection layer reads {d + 6} features, "
                           "expected appearance + 6 (box, confidence, indicator)")
    trunk = Trunk(glob_channels=glob, action_embed=action["kernel"].shape[1],
                  fuse_channels=fuse, hidden=H, lstm_layers=layers, form="release")
    model = NavModel(encoder, trunk, prev_action="probs")
    tree = {"encoder": enc_params, "trunk": trunk_params}
    _check_model_shapes(kind, model, tree, G, d)
    params = jax.tree_util.tree_map(jnp.asarray, {"params": tree})
    net = ReleaseNet(kind, model, params)
    if kind == "MetaMemoryGraphModel":
        tpn, tpn_params = _tpn(sd, H)
        net = dataclasses.replace(net, tpn=tpn, tpn_params=tpn_params)
    return net


def _nonzero(sd: dict, name: str, n: int, what: str) -> None:
    """ReleaseError naming `name` when a width read from it is 0."""
    if n < 1:
        raise ReleaseError(f"state dict: {name!r} has shape {np.shape(sd[name])}: 0 {what}, "
                           "expected at least 1 (a layer of zero width)")


def _check_finite(sd: dict) -> None:
    """Every float entry finite as float32: ReleaseError naming the first that is not."""
    for name in sorted(sd):
        x = np.asarray(sd[name])
        if not np.issubdtype(x.dtype, np.floating):
            continue                             # _get names a non-float entry it reads
        with np.errstate(over="ignore"):
            bad = int(np.size(x) - np.isfinite(x.astype(np.float32)).sum())
        if bad:
            raise ReleaseError(f"state dict: {name!r} holds {bad} non-finite value(s) (nan, "
                               "inf or beyond float32): expected finite weights (a damaged "
                               "or diverged checkpoint?)")


def _torch_name(kind: str, path: tuple[str, ...]) -> str:
    """The state-dict entry one of our parameters comes from (for messages)."""
    part, module = path[0], path[1]
    if part == "trunk":
        if module.startswith("lstm_"):
            return f"lstm.*_l{module[5:]}"
        return {"global_1x1": "conv1", "action_dense": "embed_action", "fuse_1x1": "pointwise",
                "actor": "actor_linear", "critic_hidden": "critic_linear_1",
                "critic": "critic_linear_2"}.get(module, module)
    if module.startswith("relation_"):
        return f"graph_detection_other_info_linear_{module[9:]}"
    return {"hidden": "graph_detection_feature.0",
            "to_map": "detection_feature" if kind == "BaseModel"
            else "graph_detection_feature.2"}.get(module, module)


def _check_model_shapes(kind: str, model: NavModel, tree: dict, G: int, d: int) -> None:
    """The parameters mapped from the state dict against those the model builds for 22
    categories and the inferred scene feature widths G, d (shapes only, no compute):
    every width `load` inferred must be one the model can take. ReleaseError naming the
    entry."""
    like = jax.eval_shape(lambda: model.init(
        {"params": jax.random.PRNGKey(0)}, dummy_inputs(NUM_CATEGORIES, G, d),
        model.initial_carry(1)))["params"]
    ours = {tuple(k.key for k in p): np.shape(x)
            for p, x in jax.tree_util.tree_leaves_with_path(tree)}
    want = {tuple(k.key for k in p): tuple(x.shape)
            for p, x in jax.tree_util.tree_leaves_with_path(like)}
    for path in sorted(set(ours) | set(want)):
        if ours.get(path) != want.get(path):
            raise ReleaseError(
                f"state dict: {_torch_name(kind, path)!r} gives {'/'.join(path)} the shape "
                f"{ours.get(path, 'absent')}, expected {want.get(path, 'no such parameter')} "
                f"for a {kind} of these widths (global map {G}, appearance {d}, "
                f"{NUM_CATEGORIES} categories)")


def _tpn(sd: dict, hidden: int):
    """The TPN head of a MetaMemoryGraphModel -> (TPN module, its variables); every shape
    checked against the module's (Linear -> Dense kernel, LayerNorm weight -> scale)."""
    embed = _get(sd, "meta_current_action_embedding.weight", 2).shape[0]
    tpn = TPN(hidden=hidden, action_embed=embed)
    like = jax.eval_shape(tpn.init, jax.random.PRNGKey(0), jnp.zeros((1, 1, hidden)),
                          jnp.zeros((1, 1, NUM_ACTIONS)), jnp.ones((1, 1), bool))["params"]
    params = {}
    for name, ours in RELEASE_TPN.items():
        want = like[ours]
        if "scale" in want:                                     # a LayerNorm
            w, b = _get(sd, f"{name}.weight", 1), _get(sd, f"{name}.bias", 1)
            _expect(f"{name}.weight", w, want["scale"].shape)
            _expect(f"{name}.bias", b, want["bias"].shape)
            params[ours] = {"scale": w, "bias": b}
        else:
            n_in, n_out = want["kernel"].shape
            params[ours] = _dense(sd, name, n_in=n_in, n_out=n_out)
    return tpn, jax.tree_util.tree_map(jnp.asarray, {"params": params})


def read_checkpoint(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A release checkpoint -> {name: numpy array}: a `.dat`/`.pt` file of
    `torch.save(model.state_dict(), path)` (needs torch: pip install
    'orgnav_jax[release]'), or a `.npz` of the same names (numpy only)."""
    path = os.fspath(path)
    want = "expected a release checkpoint: a torch state dict, .dat, or an .npz of one"
    if os.path.isdir(path):
        raise ReleaseError(f"{path}: a directory, {want} (a file)")
    if not os.path.isfile(path):
        raise ReleaseError(f"{path}: no such file ({want})")
    if os.path.getsize(path) == 0:
        raise ReleaseError(f"{path}: an empty file (0 bytes; an interrupted download?), "
                           f"{want}")
    if path.lower().endswith(".npz"):      # (.NPZ too: it was read as a torch file)
        try:
            z = np.load(path, allow_pickle=False)
            if not isinstance(z, np.lib.npyio.NpzFile):
                raise ValueError("a single .npy array, not an archive of named arrays")
            with z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile,
                zlib.error) as e:
            first = (str(e).splitlines() or [""])[0]
            raise ReleaseError(f"{path}: not a readable .npz ({type(e).__name__}: {first}; "
                               "a truncated file, an interrupted download?)") from None
    try:
        import torch  # optional (the release extra) and heavy: only a .dat checkpoint needs it
    except ImportError:
        raise ReleaseError(f"{path}: reading a torch checkpoint needs torch: pip install "
                           "'orgnav_jax[release]' (or save the state dict as .npz)") from None
    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001  (torch raises many kinds on a bad file)
        first = str(e).splitlines()[0] if str(e) else ""
        raise ReleaseError(f"{path}: not a torch state dict ({type(e).__name__}: "
                           f"{first})") from None
    if not isinstance(sd, dict) or not all(hasattr(v, "numpy") for v in sd.values()):
        raise ReleaseError(f"{path}: expected a state dict {{name: tensor}}")
    return {k: v.detach().cpu().numpy() for k, v in sd.items()}
