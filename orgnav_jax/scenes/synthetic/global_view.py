"""The 7x7 "global feature" code of every state: a small ray caster under jit.

For each state and each of the 7x7 image cells, a ray from the eye through the cell's
centre is marched over the room grid until it hits the floor, a wall, furniture, an
object or the ceiling. The code of that cell is GLOBAL_CODE_DIM numbers: one-hot of
what was hit (floor, wall, furniture, object, ceiling), the depth, and a fixed
3-d embedding of the furniture kind or object category hit. `features.decode_global`
projects it to G channels with a fixed random matrix, standing in for ResNet-18.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from orgnav_jax.constants import (
    CAMERA_HEIGHT, FEATURE_GRID, GRID_SIZE, HORIZONS, NUM_CATEGORIES, NUM_HEADINGS,
    ROTATION_STEP,
)
from orgnav_jax.scenes.synthetic.catalog import FURNITURE
from orgnav_jax.scenes.synthetic.geometry import STATES_PER_CELL

GLOBAL_CODE_DIM = 12
MARCH_STEP = 0.06     # metres between ray samples
MARCH_SAMPLES = 80    # rays end after 4.8 m
CEILING = 2.6         # metres
GRID_PAD = 32         # rooms are padded to a 32x32 grid for one compiled caster
CELL_CHUNK = 32       # cells per lax.map step (bounds memory)
_EMBED = np.random.default_rng(1234)  # fixed: the same embeddings for every build
FURNITURE_EMBED = _EMBED.normal(0, 1, (len(FURNITURE), 3)).astype(np.float32)
CATEGORY_EMBED = _EMBED.normal(0, 1, (NUM_CATEGORIES, 3)).astype(np.float32)


def _ray_table() -> tuple[np.ndarray, np.ndarray]:
    """Horizontal unit direction (16, 49, 2) [dx, dz] and slope dy/dh (16, 49) for every
    (heading, horizon) state-in-cell and image cell (row-major, row 0 at the top)."""
    dirs, slopes = [], []
    centres = (np.arange(FEATURE_GRID) + 0.5) / FEATURE_GRID * 2 - 1
    for h in range(NUM_HEADINGS):
        for horizon in HORIZONS:
            th, ph = np.deg2rad(h * ROTATION_STEP), np.deg2rad(horizon)
            heading = np.array([np.sin(th), 0, np.cos(th)])
            right = np.array([np.cos(th), 0, -np.sin(th)])
            fwd = np.cos(ph) * heading - np.sin(ph) * np.array([0, 1, 0])
            up = np.sin(ph) * heading + np.cos(ph) * np.array([0, 1, 0])
            d = (fwd[None, None] + centres[None, :, None] * right
                 - centres[:, None, None] * up).reshape(-1, 3)  # rows top->bottom
            nh = np.hypot(d[:, 0], d[:, 2])
            dirs.append(np.stack([d[:, 0] / nh, d[:, 2] / nh], 1))
            slopes.append(d[:, 1] / nh)
    return np.asarray(dirs, np.float32), np.asarray(slopes, np.float32)


RAY_DIR, RAY_SLOPE = _ray_table()


@jax.jit
def _cast(cells, wall, block_h, furn, obj_lo, obj_hi, obj_cat):
    """cells (M, 2) with M a multiple of CELL_CHUNK; grids (GRID_PAD, GRID_PAD).
    Returns (M, 16, 49, GLOBAL_CODE_DIM) float32."""
    t = (jnp.arange(MARCH_SAMPLES) + 0.5) * MARCH_STEP                # (N,)
    ray_dir, ray_slope = jnp.asarray(RAY_DIR), jnp.asarray(RAY_SLOPE)
    f_emb, c_emb = jnp.asarray(FURNITURE_EMBED), jnp.asarray(CATEGORY_EMBED)

    def one_cell(cell):
        eye = cell[::-1].astype(jnp.float32) * GRID_SIZE               # x, z
        px = eye[0] + ray_dir[..., 0, None] * t                         # (16, 49, N)
        pz = eye[1] + ray_dir[..., 1, None] * t
        h = CAMERA_HEIGHT + ray_slope[..., None] * t
        ci = jnp.clip(jnp.rint(pz / GRID_SIZE).astype(jnp.int32), 0, GRID_PAD - 1)
        cj = jnp.clip(jnp.rint(px / GRID_SIZE).astype(jnp.int32), 0, GRID_PAD - 1)
        is_wall = wall[ci, cj]
        is_obj = (obj_cat[ci, cj] >= 0) & (h >= obj_lo[ci, cj]) & (h <= obj_hi[ci, cj])
        is_furn = (h < block_h[ci, cj]) & (block_h[ci, cj] > 0)
        is_floor = h <= 0
        is_ceil = h >= CEILING
        kind = jnp.select([is_wall, is_obj, is_furn, is_floor, is_ceil],
                          [1, 3, 2, 0, 4], default=-1)
        kind = kind.at[..., -1].set(jnp.where(kind[..., -1] < 0, 4, kind[..., -1]))
        first = jnp.argmax(kind >= 0, axis=-1)                          # (16, 49)
        k = jnp.take_along_axis(kind, first[..., None], -1)[..., 0]
        hi = jnp.take_along_axis(ci, first[..., None], -1)[..., 0]
        hj = jnp.take_along_axis(cj, first[..., None], -1)[..., 0]
        depth = t[first] / (MARCH_SAMPLES * MARCH_STEP)
        fe = jnp.where((k == 2)[..., None] & (furn[hi, hj] >= 0)[..., None],
                       f_emb[jnp.maximum(furn[hi, hj], 0)], 0.0)
        ce = jnp.where((k == 3)[..., None], c_emb[jnp.maximum(obj_cat[hi, hj], 0)], 0.0)
        return jnp.concatenate([jax.nn.one_hot(k, 5), depth[..., None], fe, ce], -1)

    chunks = cells.reshape(-1, CELL_CHUNK, 2)
    out = jax.lax.map(jax.vmap(one_cell), chunks)
    return out.reshape(cells.shape[0], STATES_PER_CELL, FEATURE_GRID ** 2, GLOBAL_CODE_DIM)


def rasterize_objects(shape, obj_center, obj_size, obj_height, obj_category):
    """Objects -> per-cell (lo, hi, category) of the tallest object there; (H, W) each."""
    lo = np.zeros(shape, np.float32)
    hi = np.full(shape, -1.0, np.float32)
    cat = np.full(shape, -1, np.int32)
    order = np.argsort(obj_height)  # taller objects written last win
    for k in order:
        x, y, z = obj_center[k]
        r = max(obj_size[k] / 2 - 0.01, 0.0)
        for i in range(int(round((z - r) / GRID_SIZE)), int(round((z + r) / GRID_SIZE)) + 1):
            for j in range(int(round((x - r) / GRID_SIZE)), int(round((x + r) / GRID_SIZE)) + 1):
                if 0 <= i < shape[0] and 0 <= j < shape[1]:
                    lo[i, j] = y - obj_height[k] / 2
                    hi[i, j] = y + obj_height[k] / 2
                    cat[i, j] = obj_category[k]
    return lo, hi, cat


def global_codes(room, cells: np.ndarray) -> np.ndarray:
    """Room + (M, 2) reachable cells -> (M*16, 7, 7, GLOBAL_CODE_DIM) float32 codes."""
    H, W = room.wall.shape
    if H > GRID_PAD or W > GRID_PAD:
        raise ValueError(f"room {room.name} grid {H}x{W} exceeds GRID_PAD={GRID_PAD}")

    def pad(a, value):
        out = np.full((GRID_PAD, GRID_PAD), value, a.dtype)
        out[:H, :W] = a
        return out

    lo, hi, cat = rasterize_objects((H, W), room.obj_center, room.obj_size, room.obj_height,
                                    room.obj_category)
    m = len(cells)
    m_pad = -(-m // 128) * 128  # a few fixed sizes: the caster compiles a few times only
    cells_p = np.zeros((m_pad, 2), np.int32)
    cells_p[:m] = cells
    out = _cast(jnp.asarray(cells_p), jnp.asarray(pad(room.wall, True)),
                jnp.asarray(pad(room.block_height.astype(np.float32), np.inf)),
                jnp.asarray(pad(room.furniture.astype(np.int32), -1)),
                jnp.asarray(pad(lo, 0.0)), jnp.asarray(pad(hi, -1.0)), jnp.asarray(pad(cat, -1)))
    out = np.asarray(out)[:m]
    return out.reshape(m * STATES_PER_CELL, FEATURE_GRID, FEATURE_GRID, GLOBAL_CODE_DIM)
