"""A navigation model = a detection encoder + the trunk; and its inputs from observations.

    model = build_model(cfg, train_scenes)
    inputs = model_inputs(scenes, obs)                     # batched Observation -> arrays
    logits, value, carry, h = model.apply(params, inputs, carry)
    gates = model.apply(params, inputs, method=model.embed)    # the non-recurrent part
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from orgnav_jax.constants import FEATURE_GRID, IMAGE_SIZE
from orgnav_jax.models.encoders import BaselineEncoder, WordEmbeddingEncoder
from orgnav_jax.models.org import ORGEncoder, ReleasedORGEncoder, dsp_from_scenes
from orgnav_jax.models.trunk import Trunk
from orgnav_jax.scenes.features import gather_features


class ModelInputs(NamedTuple):
    glob: jax.Array         # (B, 7, 7, G) global feature map
    app: jax.Array          # (B, C, d) appearance features (0 where not detected)
    box: jax.Array          # (B, C, 4) detection boxes scaled to [0, 1]
    conf: jax.Array         # (B, C) confidences
    target: jax.Array       # (B, C) target one-hot
    prev_action: jax.Array  # (B, 6) previous action one-hot
    drop: jax.Array | None = None   # (B, 7, 7, glob_channels) dropout mask; None = no dropout


def model_inputs(scenes, obs) -> ModelInputs:
    """Gather a batched env.Observation's large features from the SceneSet (inside jit)."""
    glob, app, box, conf = gather_features(scenes, obs.state)   # global flat states
    return ModelInputs(glob, app, box / IMAGE_SIZE, conf, obs.target, obs.prev_action)


class NavModel(nn.Module):
    encoder: nn.Module
    trunk: Trunk

    def embed(self, inputs: ModelInputs, train: bool = False):
        """The non-recurrent part: inputs (B, ...) -> first LSTM layer's input gates (B, 4H)."""
        maps = self.encoder(inputs.app, inputs.box, inputs.conf, inputs.target, train)
        return self.trunk.embed(inputs.glob, maps, inputs.prev_action, inputs.drop)

    def recur(self, gates, carry):
        """Input gates (B, 4H), carry -> (logits (B, 6), value (B,), carry, LSTM output)."""
        return self.trunk.recur(gates, carry)

    def __call__(self, inputs: ModelInputs, carry, train: bool = False):
        """-> (logits (B, 6), value (B,), new carry, LSTM output (B, hidden))."""
        return self.recur(self.embed(inputs, train), carry)

    def initial_carry(self, batch: int):
        return self.trunk.initial_carry(batch)

    def dropout_shape(self, batch: int) -> tuple[int, ...]:
        """Shape of the trunk's dropout mask for a batch (see models.trunk.dropout_mask)."""
        return (batch, FEATURE_GRID, FEATURE_GRID, self.trunk.glob_channels)


def compute_dtype(cfg):
    """The modules' compute dtype for a config's `dtype` field: None (float32 as it is)
    or jnp.bfloat16 (mixed precision, float32 parameters: models/trunk.py)."""
    return {"float32": None, "bfloat16": jnp.bfloat16}[getattr(cfg, "dtype", "float32")]


# name -> factory(model config, training SceneSet) -> encoder module
ENCODERS: dict[str, Callable] = {
    "baseline": lambda cfg, scenes: BaselineEncoder(dtype=compute_dtype(cfg)),
    "we": lambda cfg, scenes: WordEmbeddingEncoder(dtype=compute_dtype(cfg)),
    "org": lambda cfg, scenes: ORGEncoder(dtype=compute_dtype(cfg)),
    "org_released": lambda cfg, scenes: ReleasedORGEncoder(dtype=compute_dtype(cfg)),
    "dsp": lambda cfg, scenes: dsp_from_scenes(scenes, compute_dtype(cfg)),
}


def build_model(cfg, scenes) -> NavModel:
    """The NavModel a config names (cfg.model, trunk widths); `scenes` are the training
    scenes, for encoders that need statistics of them (e.g. a prior knowledge graph)."""
    if cfg.model not in ENCODERS:
        raise ValueError(f"unknown model {cfg.model!r}: expected one of {sorted(ENCODERS)}")
    trunk = Trunk(glob_channels=cfg.glob_channels, action_embed=cfg.action_embed,
                  fuse_channels=cfg.fuse_channels, hidden=cfg.hidden,
                  lstm_layers=cfg.lstm_layers, dtype=compute_dtype(cfg))
    return NavModel(ENCODERS[cfg.model](cfg, scenes), trunk)


def init_params(model: NavModel, key: jax.Array, scenes):
    """Parameters for `model` from dummy inputs shaped like `scenes`' features."""
    C = scenes.present.shape[-1]
    inputs = ModelInputs(jnp.zeros((1, 7, 7, scenes.global_dim)),
                         jnp.zeros((1, C, scenes.appearance_dim)), jnp.zeros((1, C, 4)),
                         jnp.zeros((1, C)), jnp.zeros((1, C)), jnp.zeros((1, 6)))
    return model.init({"params": key}, inputs, model.initial_carry(1))
