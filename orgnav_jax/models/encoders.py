"""Per-category detection encoders: detections -> one 7x7 map per category.

Every encoder maps (app (B, C, d), box (B, C, 4) in [0, 1], conf (B, C), target (B, C))
to (B, C, 49): the per-category 7x7 maps the trunk stacks as C channels.
"""

from __future__ import annotations

from typing import Any

import flax.linen as nn
import jax.numpy as jnp

MAP_CELLS = 49  # one 7x7 map per category
# Every encoder has `dtype`: the compute dtype of its layers (None: float32; bfloat16 for
# mixed precision, parameters staying float32: models/trunk.py).


def location_features(box, conf, target):
    """The location-aware node features [box, conf, target indicator] -> (B, C, 6)."""
    return jnp.concatenate([box, conf[..., None], target[..., None]], axis=-1)


class BaselineEncoder(nn.Module):
    """The paper's Baseline: [appearance, box, conf, indicator] -> Dense 49 per category
    (weights shared across categories)."""
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        x = jnp.concatenate([app, location_features(box, conf, target)], axis=-1)
        return nn.Dense(MAP_CELLS, name="to_map", dtype=self.dtype)(x)


class WordVectorEncoder(nn.Module):
    """WE / SAVN's target input, SAVN's layout (allenai/savn models/basemodel.py:21-26,
    60-61): no detections; the target's word vector (a row of `table`, 300-d GloVe or
    the stand-in: models/word_vectors.py) -> Dense(64) -> ReLU, the same 64 values tiled
    over the 7x7 map -> (B, 64, 49), which the trunk stacks as 64 channels beside the
    global map's and the action's (64 + 64 + 10 at the release's widths)."""
    table: Any                # models.word_vectors.WordTable (C, D)
    channels: int = 64
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        vec = target @ jnp.asarray(self.table.array())           # (B, D): the target's row
        e = nn.relu(nn.Dense(self.channels, name="embed_glove", dtype=self.dtype)(vec))
        return jnp.broadcast_to(e[..., None], e.shape + (MAP_CELLS,))


class WordEmbeddingEncoder(nn.Module):
    """The WE comparison before issue 41 (target_input "onehot_maps"; runs saved before it
    keep it): no detections at all; a learned embedding of the one-hot target fills the
    C maps (22 different maps, no ReLU; not a word embedding)."""
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        num_categories = target.shape[-1]
        emb = nn.Dense(num_categories * MAP_CELLS, use_bias=False, name="target_embedding",
                       dtype=self.dtype)
        return emb(target).reshape(target.shape[:-1] + (num_categories, MAP_CELLS))
