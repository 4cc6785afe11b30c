"""The authors' initialisation, applied to a parameter tree after flax's init.

    params = release_init(params, key)

The release (`models/basemodel.py:41-62`, `utils/model_util.py`; the same in
graphmodel.py and metamemorygraphmodel.py) initialises every Linear and Conv layer with
its `weights_init` (uniform in +-sqrt(6 / (fan_in + fan_out)), i.e. Glorot uniform,
bias 0), then multiplies the global map's 1x1 kernel by the ReLU gain sqrt(2), redraws
the actor with a normalised-column init of std 0.01 and both critic layers with std 1.0
(each output unit's weight vector a normal vector scaled to that norm, bias 0), and
zeroes the LSTM's biases (its kernels keep torch's default, uniform in
+-1/sqrt(hidden)). LayerNorm scales and biases keep their (1, 0) defaults.

Here the same, by parameter name: every `kernel` (in, out) is Glorot uniform, every
`bias` 0, with the special cases above (`trunk/global_1x1`, `trunk/actor`,
`trunk/critic_hidden`, `trunk/critic`, the LSTM's `input_kernel`/`recurrent_kernel`).
Parameters of other names (ORG's learned `adjacency`, LayerNorm `scale`) are left as
flax made them.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

RELU_GAIN = math.sqrt(2.0)
NORM_COL_STD = {"actor": 0.01, "critic_hidden": 1.0, "critic": 1.0}


def glorot_uniform(key, shape):
    """Uniform in +-sqrt(6 / (fan_in + fan_out)) for a (in, out) kernel."""
    bound = math.sqrt(6.0 / (shape[0] + shape[-1]))
    return jax.random.uniform(key, shape, jnp.float32, -bound, bound)


def norm_col(key, shape, std: float):
    """A (in, out) kernel whose every output unit's weights have norm `std` (the release's
    norm_col_init, rows of torch's (out, in) weight)."""
    w = jax.random.normal(key, shape, jnp.float32)
    return w * std / jnp.sqrt((w ** 2).sum(0, keepdims=True))


def _name(path) -> tuple[str, ...]:
    return tuple(str(getattr(k, "key", getattr(k, "name", k))) for k in path)


def release_init(params, key: jax.Array):
    """params (a flax variable tree) -> the same tree with the release's initial values
    (module docstring); shapes and dtypes unchanged, deterministic in `key`."""
    leaves, treedef = jax.tree_util.tree_flatten_with_path(params)
    keys = jax.random.split(key, max(len(leaves), 1))
    out = []
    for (path, x), k in zip(leaves, keys):
        name = _name(path)
        leaf, layer = name[-1], name[-2] if len(name) > 1 else ""
        in_trunk = "trunk" in name
        if leaf == "bias":
            x = jnp.zeros_like(x)
        elif leaf in ("input_kernel", "recurrent_kernel"):       # torch's LSTM default
            bound = 1.0 / math.sqrt(x.shape[-1] // 4)
            x = jax.random.uniform(k, x.shape, x.dtype, -bound, bound)
        elif leaf == "kernel" and x.ndim == 2:
            if in_trunk and layer in NORM_COL_STD:
                x = norm_col(k, x.shape, NORM_COL_STD[layer])
            else:
                x = glorot_uniform(k, x.shape)
                if in_trunk and layer == "global_1x1":
                    x = x * RELU_GAIN
        out.append(x)
    return jax.tree_util.tree_unflatten(treedef, out)
