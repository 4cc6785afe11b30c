"""Object relation graph encoders: the paper's ORG, the authors' released form, and D-SP.

All map (app (B, C, d), box (B, C, 4) in [0, 1], conf (B, C), target (B, C)) to
(B, C, 49), like encoders.BaselineEncoder (D-SP: to those maps and a vector). 1x1
convolutions are written as Dense.

ORGEncoder (paper, Sec. 3.2), per sample, X = [box, conf, target] (C, 6), F = app (C, d):
    Z    = ReLU(A X W)            A (C, C) learned adjacency, W (6, C): Z is (C, C)
    F^   = ReLU(Z F)              parameter-free graph attention: (C, d)
    maps = Dense_49([F^, X])      weights shared across categories: (C, 49)
Z's rows index the attending category, its columns (W's outputs) the attended one, so a
relabelling of the categories by a permutation P maps A -> P A P^T and W -> W P^T.

ReleasedORGEncoder (authors' code, `models/graphmodel.py:74-85`): R1 = ReLU(X W1) (C, C)
(rows: categories, columns: W1's units); transposed once, then four C -> C ReLU layers
over what is now the category axis: R = MLP(R1^T) (C, C) (rows: W1's units j); F^ = R^T F
pairs unit j with category row j of F; [F^, X] -> Dense 128 ReLU -> Dense 49.

DSPEncoder (the paper's D-SP, issue 40): Yang et al.'s Scene Priors as SAVN's release
builds them (`allenai/savn` models/gcn.py), with detections for word embeddings. The
Baseline's path is kept unchanged (maps = Dense_49([F, X]) per category) and a graph
branch over a FIXED prior graph A_hat (co-occurrence of the training rooms,
cooccurrence_adjacency) adds a vector to the LSTM input:
    H_0 = [F, X] (C, d + 6);  H_1 = ReLU(A_hat H_0 W_0);  H_2 = ReLU(A_hat H_1 W_1)
    s = ReLU(A_hat H_2 W_2) (C, 1);  extra = Dense_out(s) (out = the LSTM width)
The encoder returns (maps, extra); the trunk concatenates `extra` to its flattened
input (models/trunk.py). Widths: W_0, W_1 square (d + 6 -> d + 6, the release's
1024 -> 1024 on its 1024-wide nodes), W_2 to 1, no biases (as the release's W0-W2); the
final map C -> LSTM width with a bias (the release's final_mapping 83 -> 512 = its
hidden size).

DSPReplaceEncoder (model "dsp_replace"; "dsp" before issue 40, config version <= 6): the
GCN *replaces* the Baseline's maps (the target's own detection is averaged with its
neighbours'): H_0 = [F, X];  H_{l+1} = ReLU(A_hat H_l W_l);  maps = Dense_49(H_L).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from orgnav_jax.errors import choose
from orgnav_jax.models.encoders import MAP_CELLS, location_features
from orgnav_jax.models.trunk import cast


def adjacency_init(noise: float = 0.0):
    """Initialiser for a (C, C) adjacency: identity plus N(0, noise^2) entries. At the start
    every category attends to its own features only (no noise by default: W is random, so
    no symmetry needs breaking, and every off-diagonal entry of a trained A is learned)."""
    def init(key, shape, dtype=jnp.float32):
        if len(shape) != 2 or shape[0] != shape[1]:
            raise ValueError(f"adjacency must be square (C, C), got shape {shape}")
        return (jnp.eye(shape[0], dtype=dtype)
                + noise * jax.random.normal(key, shape, dtype))
    return init


class ORGEncoder(nn.Module):
    """The paper's ORG: Z = ReLU(A X W) (B, C, C); F^ = ReLU(Z F) (B, C, d);
    Dense 49 over [F^, X] per category. Parameters: `adjacency` (C, C), `embed_W` (6, C),
    `to_map`."""
    adjacency_noise: float = 0.0
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        C, dt = app.shape[-2], self.dtype
        x = location_features(box, conf, target)                     # (B, C, 6)
        A = self.param("adjacency", adjacency_init(self.adjacency_noise), (C, C))
        xw = nn.Dense(C, use_bias=False, name="embed_W", dtype=dt)(x)   # X W: (B, C, C)
        z = nn.relu(jnp.einsum("ij,bjk->bik", cast(A, dt), xw))      # Z:   (B, C, C)
        f_hat = nn.relu(jnp.einsum("bik,bkd->bid", z, cast(app, dt)))   # F^: (B, C, d)
        h = jnp.concatenate([f_hat, cast(x, dt)], axis=-1)
        return nn.Dense(MAP_CELLS, name="to_map", dtype=dt)(h)


class ReleasedORGEncoder(nn.Module):
    """The authors' release (module docstring): R = MLP(ReLU(X W1)^T) (B, C, C), the four
    C -> C layers all over the category axis; F^ = R^T F (B, C, d); [F^, X] -> Dense 128
    ReLU -> Dense 49.

    wiring="alternate" is the form this project used before issue 39 (config version <= 6,
    kept so those runs evaluate as trained): the C -> C layers alternately over the
    category and the feature axis, F^ summed over the category axis."""
    hidden: int = 128
    wiring: str = "release"    # "release" | "alternate"
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        release = choose({"release": True, "alternate": False}, self.wiring,
                         "released ORG wiring")
        C, dt = app.shape[-2], self.dtype
        x = location_features(box, conf, target)                     # (B, C, 6)
        r = nn.relu(nn.Dense(C, name="relation_1", dtype=dt)(x))     # (B, C, C): [i, j]
        if release:
            r = jnp.swapaxes(r, -1, -2)                              # [j, i]
            for i in range(2, 6):
                r = nn.relu(nn.Dense(C, name=f"relation_{i}", dtype=dt)(r))   # [j, k]
            f_hat = jnp.einsum("bjk,bjd->bkd", r, cast(app, dt))     # (B, C, d)
        else:
            for i in range(2, 6):
                transpose = i % 2 == 0
                if transpose:
                    r = jnp.swapaxes(r, -1, -2)
                r = nn.relu(nn.Dense(C, name=f"relation_{i}", dtype=dt)(r))
                if transpose:
                    r = jnp.swapaxes(r, -1, -2)
            f_hat = jnp.einsum("bij,bid->bjd", r, cast(app, dt))     # R^T F: (B, C, d)
        h = jnp.concatenate([f_hat, cast(x, dt)], axis=-1)
        h = nn.relu(nn.Dense(self.hidden, name="hidden", dtype=dt)(h))
        return nn.Dense(MAP_CELLS, name="to_map", dtype=dt)(h)


def cooccurrence_adjacency(present: np.ndarray) -> np.ndarray:
    """(N, C) presence of each category in each training room -> (C, C) prior graph.

    M = P^T P counts rooms holding both categories; the edge weight is the normalised
    co-occurrence (Ochiai / cosine) M_ij / sqrt(M_ii M_jj) off the diagonal (0 where a
    category never occurs); then self-loops and symmetric normalisation:
    A_hat = D^-1/2 (A + I) D^-1/2 with D the row sums of A + I. Symmetric, >= 0."""
    p = np.asarray(present, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"present must be (N, C), got shape {p.shape}")
    m = p.T @ p
    occ = np.sqrt(np.diag(m))
    denom = np.outer(occ, occ)
    a = np.divide(m, denom, out=np.zeros_like(m), where=denom > 0)
    np.fill_diagonal(a, 0.0)
    a = a + np.eye(a.shape[0])
    d = 1.0 / np.sqrt(a.sum(1))
    return (a * d[:, None] * d[None, :]).astype(np.float32)


def as_static_matrix(a: np.ndarray) -> tuple[tuple[float, ...], ...]:
    """A (C, C) array as a hashable tuple of tuples (a module attribute)."""
    return tuple(tuple(float(v) for v in row) for row in np.asarray(a))


class DSPReplaceEncoder(nn.Module):
    """D-SP before issue 40 (model "dsp_replace"): GCN layers H <- ReLU(A_hat H W) over
    the fixed prior graph `adjacency` (C x C, hashable tuple of tuples) on nodes [F, X]
    (B, C, d + 6), then Dense 49: the graph's output replaces the detection maps."""
    adjacency: tuple[tuple[float, ...], ...]
    features: Sequence[int] = (64, 64)
    dtype: Any = None

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        A = jnp.asarray(self.adjacency, jnp.float32)
        C = app.shape[-2]
        if A.shape != (C, C):
            raise ValueError(f"D-SP adjacency is {A.shape}, inputs have {C} categories")
        h = jnp.concatenate([app, location_features(box, conf, target)], axis=-1)
        for i, width in enumerate(self.features):
            h = nn.Dense(width, name=f"gcn_{i}", dtype=self.dtype)(h)   # H W
            h = nn.relu(jnp.einsum("ij,bjk->bik", cast(A, self.dtype), h))   # A_hat H W
        return nn.Dense(MAP_CELLS, name="to_map", dtype=self.dtype)(h)


class DSPEncoder(nn.Module):
    """The paper's D-SP (module docstring): the Baseline's maps (`to_map`, the Baseline's
    parameter) and the graph branch's vector (B, out_features) -> (maps, extra). The
    branch: three graph layers `graph_0..2` (no bias, ReLU after each, the last to one
    value per node) over the fixed prior graph `adjacency`, then `graph_out` (C ->
    out_features)."""
    adjacency: tuple[tuple[float, ...], ...]
    out_features: int = 128
    dtype: Any = None

    @property
    def extra_features(self) -> int:
        """Width of the vector the trunk concatenates to its flattened LSTM input."""
        return self.out_features

    @nn.compact
    def __call__(self, app, box, conf, target, train: bool = False):
        A = jnp.asarray(self.adjacency, jnp.float32)
        C, dt = app.shape[-2], self.dtype
        if A.shape != (C, C):
            raise ValueError(f"D-SP adjacency is {A.shape}, inputs have {C} categories")
        nodes = jnp.concatenate([app, location_features(box, conf, target)], axis=-1)
        maps = nn.Dense(MAP_CELLS, name="to_map", dtype=dt)(nodes)     # the Baseline's
        h, width = cast(nodes, dt), nodes.shape[-1]
        for i, w in enumerate((width, width, 1)):          # ReLU(W(A_hat H)), as gcn.py
            h = jnp.einsum("ij,bjk->bik", cast(A, dt), h)
            h = nn.relu(nn.Dense(w, use_bias=False, name=f"graph_{i}", dtype=dt)(h))
        extra = nn.Dense(self.out_features, name="graph_out", dtype=dt)(h[..., 0])
        return maps, extra


def dsp_from_scenes(scenes, out_features: int, dtype=None) -> DSPEncoder:
    """The paper's D-SP (DSPEncoder) whose prior graph comes from `scenes.present` (the
    training rooms); out_features: the graph vector's width (the LSTM width)."""
    return DSPEncoder(as_static_matrix(cooccurrence_adjacency(np.asarray(scenes.present))),
                      out_features, dtype=dtype)


def dsp_replace_from_scenes(scenes, dtype=None) -> DSPReplaceEncoder:
    """The D-SP of config versions <= 6 (DSPReplaceEncoder), prior graph as dsp_from_scenes."""
    return DSPReplaceEncoder(
        as_static_matrix(cooccurrence_adjacency(np.asarray(scenes.present))), dtype=dtype)
