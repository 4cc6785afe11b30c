"""Decode stored feature codes into the model's inputs, inside jit.

Synthetic scenes store small 16-bit codes (see global_view.py, detector.py) and fixed
projections; imported offline data stores the features themselves (bases are None),
float16 or int8 with a per-channel scale (quantize.py): value = int8 * scale.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from orgnav_jax.scenes.sceneset.sceneset import SceneSet


def _dequantize(x: jax.Array, scale) -> jax.Array:
    x = x.astype(jnp.float32)
    return x if scale is None else x * scale


def decode_global(scenes: SceneSet, code: jax.Array) -> jax.Array:
    """(..., 7, 7, Dg) stored code -> (..., 7, 7, G) float32 feature map."""
    x = _dequantize(code, getattr(scenes, "global_scale", None))
    if scenes.global_basis is None:
        return x
    return jax.nn.relu(x @ scenes.global_basis)


def decode_appearance(scenes: SceneSet, code: jax.Array, det_conf: jax.Array) -> jax.Array:
    """(..., C, Da) code and (..., C) confidence -> (..., C, d) float32 features:
    relu(prototype[c] + code @ basis) where something was detected, else 0."""
    x = _dequantize(code, getattr(scenes, "appearance_scale", None))
    if scenes.appearance_basis is None:
        return x
    feat = jax.nn.relu(scenes.appearance_proto + x @ scenes.appearance_basis)
    return jnp.where((det_conf > 0)[..., None], feat, 0.0)


def gather_features(scenes: SceneSet, state_idx: jax.Array):
    """Global flat state indices, any shape B (EnvState.state, Observation.state) ->
    (global (B, 7, 7, G), appearance (B, C, d), det_box (B, C, 4) float32 pixels,
    det_conf (B, C) float32). A room's local index s is state_offset[n] + s."""
    conf = scenes.det_conf[state_idx].astype(jnp.float32)
    glob = decode_global(scenes, scenes.global_feat[state_idx])
    app = decode_appearance(scenes, scenes.appearance[state_idx], conf)
    box = scenes.det_box[state_idx].astype(jnp.float32)
    return glob, app, box, conf
