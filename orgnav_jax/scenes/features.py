"""Decode stored feature codes into the model's inputs, inside jit.

Synthetic scenes store small 16-bit codes (see global_view.py, detector.py) and fixed
projections; imported offline data stores the features themselves (bases are None).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from orgnav_jax.scenes.sceneset import SceneSet


def decode_global(scenes: SceneSet, code: jax.Array) -> jax.Array:
    """(..., 7, 7, Dg) stored code -> (..., 7, 7, G) float32 feature map."""
    x = code.astype(jnp.float32)
    if scenes.global_basis is None:
        return x
    return jax.nn.relu(x @ scenes.global_basis)


def decode_appearance(scenes: SceneSet, code: jax.Array, det_conf: jax.Array) -> jax.Array:
    """(..., C, Da) code and (..., C) confidence -> (..., C, d) float32 features:
    relu(prototype[c] + code @ basis) where something was detected, else 0."""
    x = code.astype(jnp.float32)
    if scenes.appearance_basis is None:
        return x
    feat = jax.nn.relu(scenes.appearance_proto + x @ scenes.appearance_basis)
    return jnp.where((det_conf > 0)[..., None], feat, 0.0)


def gather_features(scenes: SceneSet, scene_idx: jax.Array, state_idx: jax.Array):
    """Index arrays of equal shape B -> (global (B, 7, 7, G), appearance (B, C, d),
    det_box (B, C, 4) float32 pixels, det_conf (B, C) float32)."""
    conf = scenes.det_conf[scene_idx, state_idx].astype(jnp.float32)
    glob = decode_global(scenes, scenes.global_feat[scene_idx, state_idx])
    app = decode_appearance(scenes, scenes.appearance[scene_idx, state_idx], conf)
    box = scenes.det_box[scene_idx, state_idx].astype(jnp.float32)
    return glob, app, box, conf
