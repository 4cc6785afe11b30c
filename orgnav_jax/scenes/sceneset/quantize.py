"""Optional int8 storage of the large features, with a per-channel float32 scale.

    q = quantize_features(scenes)        # global_feat, appearance -> int8 + scales
    python -m orgnav_jax.scenes import ... --features int8
    python -m orgnav_jax.scenes convert OLD --out NEW --features int8

Symmetric per-channel quantization: scale[c] = max |x[..., c]| / 127 over all states
(1 where a channel is all zero), q = round(x / scale) in -127..127; decoded inside jit as
q * scale (features.py). The error of one value is at most scale[c] / 2. Halves the
feature bytes of float16 storage; for users at the memory limit (docs/benchmark.md).
"""

from __future__ import annotations

import numpy as np

from orgnav_jax.scenes.sceneset.fields import SCALE_OF

from orgnav_jax.scenes.sceneset.sceneset import SceneSet

FEATURE_DTYPES = ("float16", "int8")
QMAX = 127
CHUNK_STATES = 4096   # states converted at a time (bounds the float32 temporaries)


def channel_scale(arr: np.ndarray, chunk: int = CHUNK_STATES) -> np.ndarray:
    """(channels,) float32 max |x| / 127 over every axis but the last, streamed."""
    peak = np.zeros(arr.shape[-1], np.float32)
    for lo in range(0, arr.shape[0], chunk):
        block = np.abs(np.asarray(arr[lo:lo + chunk], np.float32))
        peak = np.maximum(peak, block.reshape(-1, arr.shape[-1]).max(0))
    scale = peak / QMAX
    return np.where(scale > 0, scale, 1.0).astype(np.float32)


def quantize_array(arr: np.ndarray, scale: np.ndarray, chunk: int = CHUNK_STATES) -> np.ndarray:
    """float array (T, ..., channels) -> int8 round(x / scale), chunk by chunk."""
    out = np.empty(arr.shape, np.int8)
    for lo in range(0, arr.shape[0], chunk):
        block = np.asarray(arr[lo:lo + chunk], np.float32) / scale
        out[lo:lo + chunk] = np.clip(np.rint(block), -QMAX, QMAX).astype(np.int8)
    return out


def quantize_features(scenes: SceneSet) -> SceneSet:
    """global_feat and appearance as int8 with per-channel scales (unchanged if already
    int8). Works on codes (synthetic sets: the scale applies before the basis) and on
    raw features (imported sets)."""
    out = {}
    for name, scale_name in SCALE_OF.items():
        arr = getattr(scenes, name)
        if np.dtype(arr.dtype) == np.int8:
            continue
        scale = channel_scale(arr)
        out[name], out[scale_name] = quantize_array(arr, scale), scale
    return scenes.replace(**out)


def dequantize_features(scenes: SceneSet, dtype=np.float16) -> SceneSet:
    """int8 features back to `dtype` (float16: the default storage), scales dropped."""
    out = {}
    for name, scale_name in SCALE_OF.items():
        arr, scale = getattr(scenes, name), getattr(scenes, scale_name)
        if scale is None:
            continue
        out[name] = (np.asarray(arr, np.float32) * np.asarray(scale)).astype(dtype)
        out[scale_name] = None
    return scenes.replace(**out)


def with_features(scenes: SceneSet, features: str | None) -> SceneSet:
    """scenes stored as `features` ('float16' or 'int8'; None keeps them as they are)."""
    if features is None:
        return scenes
    if features not in FEATURE_DTYPES:
        raise ValueError(f"--features {features!r}: expected one of {list(FEATURE_DTYPES)}")
    return quantize_features(scenes) if features == "int8" else dequantize_features(scenes)
