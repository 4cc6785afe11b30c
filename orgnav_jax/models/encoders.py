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


class WordEmbeddingEncoder(nn.Module):
    """The WE comparison: no detections at all; a learned embedding of the target category
    fills the C maps."""
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        num_categories = target.shape[-1]
        emb = nn.Dense(num_categories * MAP_CELLS, use_bias=False, name="target_embedding",
                       dtype=self.dtype)
        return emb(target).reshape(target.shape[:-1] + (num_categories, MAP_CELLS))
