"""A navigation model = a detection encoder + the trunk; and its inputs from observations.

    model = build_model(cfg, train_scenes)
    inputs = model_inputs(scenes, obs)                     # batched Observation -> arrays
    logits, value, carry, h = model.apply(params, inputs, carry)
    gates = model.apply(params, inputs, method=model.embed)    # the non-recurrent part

The previous action enters as the previous step's action probabilities (the release's
`agents/agent.py:176,184`: zeros at an episode start), kept in the carry (NavCarry.probs)
and written into the inputs by `previous_action` (`prev_action="onehot"`: the env's
one-hot of the action taken, as before issue 39). They enter as data: no gradient flows
through them into the previous step (the release backpropagates through them; here the
non-recurrent part runs once over a whole rollout, docs/training.md).
"""

from __future__ import annotations

from functools import partial
from typing import Callable, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from orgnav_jax.constants import FEATURE_GRID, IMAGE_SIZE, NUM_ACTIONS
from orgnav_jax.errors import choose
from orgnav_jax.models.encoders import (
    BaselineEncoder, WordEmbeddingEncoder, WordVectorEncoder)
from orgnav_jax.models.init import release_init
from orgnav_jax.models.org import (
    ORGEncoder, ReleasedORGEncoder, dsp_from_scenes, dsp_replace_from_scenes)
from orgnav_jax.models.trunk import Trunk, compute_dtype
from orgnav_jax.models.vtnet import VTNetEncoder
from orgnav_jax.models.word_vectors import category_table
from orgnav_jax.scenes.sceneset.features import gather_features


class ModelInputs(NamedTuple):
    glob: jax.Array         # (B, 7, 7, G) global feature map
    app: jax.Array          # (B, C, d) appearance features (0 where not detected)
    box: jax.Array          # (B, C, 4) detection boxes scaled to [0, 1]
    conf: jax.Array         # (B, C) confidences
    target: jax.Array       # (B, C) target one-hot
    prev_action: jax.Array  # (B, 6) previous action: probabilities (or a one-hot)
    drop: jax.Array | None = None   # (B, 7, 7, dropout channels) mask; None = no dropout


@struct.dataclass
class NavCarry:
    """The recurrent state: lstm, per layer (c, h), each (B, hidden); probs (B, 6), the
    previous step's action probabilities (zeros at an episode start)."""
    lstm: tuple
    probs: jax.Array


def model_inputs(scenes, obs) -> ModelInputs:
    """Gather a batched env.Observation's large features from the SceneSet (inside jit).
    prev_action is the env's one-hot; `previous_action` puts the model's input there."""
    glob, app, box, conf = gather_features(scenes, obs.state)   # global flat states
    return ModelInputs(glob, app, box / IMAGE_SIZE, conf, obs.target, obs.prev_action)


class NavModel(nn.Module):
    encoder: nn.Module
    trunk: Trunk
    prev_action: str = "probs"      # "probs" (release) | "onehot" (module docstring)

    def embed(self, inputs: ModelInputs, train: bool = False):
        """The non-recurrent part: inputs (B, ...) -> first LSTM layer's input gates (B, 4H).
        inputs.prev_action is used as given (see previous_action)."""
        maps = self.encoder(inputs.app, inputs.box, inputs.conf, inputs.target, train)
        maps, extra = maps if isinstance(maps, tuple) else (maps, None)
        return self.trunk.embed(inputs.glob, maps, inputs.prev_action, inputs.drop, extra)

    def recur(self, gates, carry: NavCarry):
        """Input gates (B, 4H), carry -> (logits (B, 6), value (B,), carry, LSTM output);
        the new carry holds this step's action probabilities."""
        carry, h = self.lstm_step(gates, carry)
        logits, value = self.actor_critic(h)
        return logits, value, self.with_probs(carry, logits), h

    def lstm_step(self, gates, carry: NavCarry):
        """The recurrence without the heads: -> (carry with the LSTM state advanced and
        the probabilities as they were, LSTM output (B, H)); see with_probs."""
        lstm, h = self.trunk.lstm_step(gates, carry.lstm)
        return carry.replace(lstm=lstm), h

    def actor_critic(self, h):
        """LSTM output (..., H) -> (logits (..., 6), value (...))."""
        return self.trunk.actor_critic(h)

    @staticmethod
    def with_probs(carry: NavCarry, logits) -> NavCarry:
        """The carry holding the action probabilities of `logits` (B, 6) (no gradient)."""
        probs = jax.lax.stop_gradient(jax.nn.softmax(logits)).astype(carry.probs.dtype)
        return carry.replace(probs=probs)

    def __call__(self, inputs: ModelInputs, carry: NavCarry, train: bool = False):
        """One step from the env's inputs -> (logits (B, 6), value (B,), new carry, LSTM
        output (B, hidden))."""
        inputs = inputs._replace(prev_action=previous_action(self, inputs.prev_action, carry))
        return self.recur(self.embed(inputs, train), carry)

    def initial_carry(self, batch: int) -> NavCarry:
        return NavCarry(self.trunk.initial_carry(batch),
                        jnp.zeros((batch, NUM_ACTIONS), jnp.float32))

    def dropout_shape(self, batch: int) -> tuple[int, ...]:
        """Shape of the trunk's dropout mask for a batch (see models.trunk.dropout_mask)."""
        return (batch, FEATURE_GRID, FEATURE_GRID, self.trunk.dropout_channels())


def previous_action(model: NavModel, onehot: jax.Array, carry: NavCarry) -> jax.Array:
    """The previous-action input (B, 6) of a step: the carry's probabilities (release), or
    the env's one-hot `onehot` (prev_action="onehot"). Pure: usable outside apply (the
    rollout stores it in its trajectory so that the loss's replay sees the same input)."""
    return choose({"probs": carry.probs, "onehot": onehot}, model.prev_action,
                  "previous-action input (prev_action)")


def we_encoder(cfg):
    """WE / SAVN's target input (cfg.target_input): SAVN's word-vector layout, or the
    one-hot maps of runs saved before issue 41 (docs/savn.md)."""
    return choose({
        "word_vector": lambda: WordVectorEncoder(
            category_table(getattr(cfg, "word_vectors", None)), dtype=compute_dtype(cfg)),
        "onehot_maps": lambda: WordEmbeddingEncoder(dtype=compute_dtype(cfg))},
        getattr(cfg, "target_input", "word_vector"), "WE target input (target_input)")()


# name -> factory(model config, training SceneSet) -> encoder module (one with a
# `build_trunk(cfg)` method brings its own trunk: build_model)
ENCODERS: dict[str, Callable] = {
    "baseline": lambda cfg, scenes: BaselineEncoder(dtype=compute_dtype(cfg)),
    "we": lambda cfg, scenes: we_encoder(cfg),
    "org": lambda cfg, scenes: ORGEncoder(dtype=compute_dtype(cfg)),
    "org_released": lambda cfg, scenes: ReleasedORGEncoder(
        wiring="release" if cfg.net == "release" else "alternate", dtype=compute_dtype(cfg)),
    # D-SP as the paper built it (SAVN's release gcn.py): the Baseline plus a graph
    # branch whose vector (the LSTM width) joins the LSTM input (models/org.py)
    "dsp": lambda cfg, scenes: dsp_from_scenes(scenes, cfg.hidden, compute_dtype(cfg)),
    # D-SP before issue 40 (config version <= 6 "dsp"): the graph replaces the maps
    "dsp_replace": lambda cfg, scenes: dsp_replace_from_scenes(scenes, compute_dtype(cfg)),
    # VTNet (issue 43): a transformer encoder over the detections; its own trunk (the
    # decoder queried by the global map's cells, then the LSTM policy: models/vtnet.py)
    "vtnet": lambda cfg, scenes: vtnet_encoder(cfg),
}


def vtnet_encoder(cfg):
    """VTNet's encoder at the config's widths (models/vtnet.py; docs/vtnet.md)."""
    return VTNetEncoder(dim=cfg.vtnet_dim, heads=cfg.vtnet_heads, ffn=cfg.vtnet_ffn,
                        layers=cfg.vtnet_encoder_layers, mask=cfg.vtnet_mask,
                        dtype=compute_dtype(cfg))


def build_model(cfg, scenes) -> NavModel:
    """The NavModel a config names (cfg.model, trunk widths); `scenes` are the training
    scenes, for encoders that need statistics of them (e.g. a prior knowledge graph)."""
    if cfg.model not in ENCODERS:
        raise ValueError(f"unknown model {cfg.model!r}: expected one of {sorted(ENCODERS)}")
    encoder = ENCODERS[cfg.model](cfg, scenes)
    if hasattr(encoder, "build_trunk"):      # an encoder with a trunk of its own (VTNet)
        return NavModel(encoder, encoder.build_trunk(cfg), cfg.prev_action)
    trunk = Trunk(glob_channels=cfg.glob_channels, action_embed=cfg.action_embed,
                  fuse_channels=cfg.fuse_channels, hidden=cfg.hidden,
                  lstm_layers=cfg.lstm_layers, dtype=compute_dtype(cfg), form=cfg.net,
                  extra_features=getattr(encoder, "extra_features", 0))
    return NavModel(encoder, trunk, cfg.prev_action)


def init_params(model: NavModel, key: jax.Array, scenes):
    """Parameters for `model` from dummy inputs shaped like `scenes`' features.

    One jitted program per model and feature widths (jax's cache: the module is a static,
    hashable argument). Run op by op, a process's first initialisation compiled every
    primitive on its own: 4.7 s here against 2.5 s for the program, and the same bits."""
    return _init_params(model, key, scenes.present.shape[-1], scenes.global_dim,
                        scenes.appearance_dim)


def dummy_inputs(num_categories: int, global_dim: int, appearance_dim: int) -> ModelInputs:
    """Zero ModelInputs of batch 1 with the given feature widths (what init traces)."""
    C = num_categories
    return ModelInputs(jnp.zeros((1, FEATURE_GRID, FEATURE_GRID, global_dim)),
                       jnp.zeros((1, C, appearance_dim)), jnp.zeros((1, C, 4)),
                       jnp.zeros((1, C)), jnp.zeros((1, C)), jnp.zeros((1, 6)))


@partial(jax.jit, static_argnums=(0, 2, 3, 4))
def _init_params(model: NavModel, key: jax.Array, num_categories: int, global_dim: int,
                 appearance_dim: int):
    inputs = dummy_inputs(num_categories, global_dim, appearance_dim)
    params = model.init({"params": key}, inputs, model.initial_carry(1))
    if model.trunk.form == "release":          # the release's initialisation (models/init.py)
        params = release_init(params, jax.random.fold_in(key, 1))
    return params


# The feature widths a model is built for are in its parameters' shapes: the trunk's
# global 1x1 layer reads the G channels of the global map, and each encoder's first layer
# over the nodes [appearance (d), location (6)] has d + 6 input rows (the first of these
# layers an encoder has; the WE encoder reads no appearance).
GLOBAL_INPUT = "trunk/global_1x1/kernel"
APPEARANCE_INPUTS = ("encoder/gcn_0/kernel", "encoder/hidden/kernel", "encoder/to_map/kernel")
LOCATION_FEATURES = 6
APPEARANCE_ONLY_INPUT = "encoder/local_0/kernel"    # VTNet's: d rows (the appearance alone)


def _path_name(path) -> str:
    return "/".join(str(getattr(k, "key", getattr(k, "name", getattr(k, "idx", k))))
                    for k in path)


def feature_widths(params) -> dict[str, int]:
    """The scene feature widths parameters were built for -> {"global_dim": G,
    "appearance_dim": d} (either absent when the parameters do not show it). `params`:
    any tree holding a NavModel's parameters (arrays, shapes, or a checkpoint's array
    metadata: a training runner, a TPN policy's {"base", "tpn"}), read from shapes only."""
    shapes = {_path_name(p): tuple(getattr(x, "shape", ()))
              for p, x in jax.tree_util.tree_leaves_with_path(params)}
    out = {}
    for path, shape in shapes.items():
        if path.endswith(GLOBAL_INPUT) and len(shape) == 2:
            out.setdefault("global_dim", shape[0])
    if "encoder/target_embedding/kernel" not in "|".join(shapes):
        for name, extra in ((n, LOCATION_FEATURES) for n in APPEARANCE_INPUTS):
            rows = [s[0] for p, s in shapes.items() if p.endswith(name) and len(s) == 2]
            if rows:
                out["appearance_dim"] = rows[0] - extra
                break
        rows = [s[0] for p, s in shapes.items()
                if p.endswith(APPEARANCE_ONLY_INPUT) and len(s) == 2]
        if rows and "appearance_dim" not in out:
            out["appearance_dim"] = rows[0]
    return out


def check_feature_widths(trained: dict[str, int], scenes, what: str, scenes_name: str) -> None:
    """ValueError (one line) when `scenes`' feature widths differ from the ones a model
    was `trained` on (feature_widths): `what` names the model (a checkpoint, a run),
    scenes_name the scenes. Checked before a model is built or applied (else flax fails
    deep inside with a parameter shape error)."""
    have = {"global_dim": scenes.global_dim, "appearance_dim": scenes.appearance_dim}
    diff = [k for k in trained if trained[k] != have[k]]
    if diff:
        def words(w):
            return ", ".join(f"{k} {w[k]}" for k in diff)
        raise ValueError(f"{what} was trained on scene features of {words(trained)}, but "
                         f"scenes {scenes_name} have {words(have)}: use scenes with the "
                         "feature widths the model was trained on")
