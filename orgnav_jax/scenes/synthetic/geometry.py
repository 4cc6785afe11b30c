"""States, transitions, the camera model, line of sight and visibility (numpy).

A state is (reachable cell m, heading h in 0..7, horizon v in 0..1) with index
s = m * 16 + h * 2 + v; cells are the room's reachable cells in row-major order.
Heading h points along HEADING_STEP[h] = (di, dj): 0 deg -> +z (di=+1), 90 deg -> +x.
"""

from __future__ import annotations

import numpy as np

from orgnav_jax import constants
from orgnav_jax.constants import (
    CAMERA_HEIGHT, DONE, GRID_SIZE, HORIZONS, LOOK_DOWN, LOOK_UP, MOVE_AHEAD, NUM_ACTIONS,
    NUM_HEADINGS, ROTATE_LEFT, ROTATE_RIGHT, ROTATION_STEP, VISIBILITY_DISTANCE,
)

STATES_PER_CELL = NUM_HEADINGS * len(HORIZONS)  # 16
HEADING_STEP = np.array(constants.HEADING_STEP)  # (8, 2) (di, dj) of MoveAhead per heading
LOS_STEP = 0.05  # metres between line-of-sight samples


def reachable_cells(reachable: np.ndarray) -> np.ndarray:
    """(H, W) bool -> (M, 2) int cell coordinates (i, j), row-major order."""
    return np.argwhere(reachable)


def state_poses(cells: np.ndarray) -> np.ndarray:
    """(M, 2) cells -> (M*16, 4) float32 poses: x, z, rotation (deg), horizon (deg)."""
    m = np.repeat(np.arange(len(cells)), STATES_PER_CELL)
    h = np.tile(np.repeat(np.arange(NUM_HEADINGS), len(HORIZONS)), len(cells))
    v = np.tile(np.arange(len(HORIZONS)), len(cells) * NUM_HEADINGS)
    return np.stack([cells[m, 1] * GRID_SIZE, cells[m, 0] * GRID_SIZE,
                     h * ROTATION_STEP, np.asarray(HORIZONS)[v]], axis=1).astype(np.float32)


def transitions(cells: np.ndarray, grid_shape: tuple[int, int]) -> np.ndarray:
    """(M, 2) reachable cells -> (M*16, 6) int32 successor state per action.

    MoveAhead into a cell that is not reachable fails (stays put); LookUp only from
    horizon 30, LookDown only from 0; Done stays.
    """
    index = np.full(grid_shape, -1, np.int64)
    index[cells[:, 0], cells[:, 1]] = np.arange(len(cells))
    S = len(cells) * STATES_PER_CELL
    s = np.arange(S)
    m, h, v = s // STATES_PER_CELL, (s // 2) % NUM_HEADINGS, s % 2
    nxt = np.empty((S, NUM_ACTIONS), np.int64)
    ti = cells[m, 0] + HEADING_STEP[h, 0]
    tj = cells[m, 1] + HEADING_STEP[h, 1]
    inside = (ti >= 0) & (ti < grid_shape[0]) & (tj >= 0) & (tj < grid_shape[1])
    target = np.where(inside, index[np.clip(ti, 0, grid_shape[0] - 1),
                                    np.clip(tj, 0, grid_shape[1] - 1)], -1)
    nxt[:, MOVE_AHEAD] = np.where(target >= 0, target * STATES_PER_CELL + h * 2 + v, s)
    nxt[:, ROTATE_LEFT] = m * STATES_PER_CELL + ((h - 1) % NUM_HEADINGS) * 2 + v
    nxt[:, ROTATE_RIGHT] = m * STATES_PER_CELL + ((h + 1) % NUM_HEADINGS) * 2 + v
    nxt[:, LOOK_UP] = np.where(v == 1, s - 1, s)
    nxt[:, LOOK_DOWN] = np.where(v == 0, s + 1, s)
    nxt[:, DONE] = s
    return nxt.astype(np.int32)


def camera_frames(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(S, 4) poses -> right, up, forward unit vectors, each (S, 3) in world (x, y, z)."""
    th = np.deg2rad(poses[:, 2])
    ph = np.deg2rad(poses[:, 3])
    zero = np.zeros_like(th)
    heading = np.stack([np.sin(th), zero, np.cos(th)], 1)
    right = np.stack([np.cos(th), zero, -np.sin(th)], 1)
    world_up = np.array([0.0, 1.0, 0.0])
    forward = np.cos(ph)[:, None] * heading - np.sin(ph)[:, None] * world_up
    up = np.sin(ph)[:, None] * heading + np.cos(ph)[:, None] * world_up
    return right, up, forward


def to_camera(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (K, 3) world (x, y, z) seen from every pose -> (S, K, 3) camera coords
    (x right, y up, z forward); the eye is at (pose x, CAMERA_HEIGHT, pose z)."""
    right, up, forward = camera_frames(poses)
    eye = np.stack([poses[:, 0], np.full(len(poses), CAMERA_HEIGHT), poses[:, 1]], 1)
    rel = points[None, :, :] - eye[:, None, :]
    return np.stack([np.einsum("skd,sd->sk", rel, right),
                     np.einsum("skd,sd->sk", rel, up),
                     np.einsum("skd,sd->sk", rel, forward)], axis=-1)


def in_view(cam: np.ndarray) -> np.ndarray:
    """(..., 3) camera coords -> bool: inside the 90 deg x 90 deg frustum."""
    x, y, z = cam[..., 0], cam[..., 1], cam[..., 2]
    return (z > 1e-6) & (np.abs(x) <= z) & (np.abs(y) <= z)


def line_of_sight(block_height: np.ndarray, cells: np.ndarray, obj_center: np.ndarray,
                  obj_size: np.ndarray, max_dist: float) -> np.ndarray:
    """(M, K) bool: the segment from the eye above each cell to each object centre is
    not blocked by walls, furniture or blocking objects taller than the segment.

    Samples every LOS_STEP metres up to the object's own footprint (which never hides
    the object itself). block_height is (H, W) with inf on walls.
    """
    H, W = block_height.shape
    eye = cells[:, ::-1].astype(np.float64) * GRID_SIZE            # (M, 2) x, z
    tgt = obj_center[:, [0, 2]].astype(np.float64)                 # (K, 2)
    delta = tgt[None] - eye[:, None]                               # (M, K, 2)
    dist = np.linalg.norm(delta, axis=-1)                          # (M, K)
    stop = dist - (obj_size[None] / 2 + GRID_SIZE / 2)
    t = np.arange(1, int(np.ceil(max_dist / LOS_STEP)) + 1) * LOS_STEP  # (T,)
    frac = t[None, None, :] / np.maximum(dist[..., None], 1e-6)     # (M, K, T)
    px = eye[:, None, None, 0] + delta[..., None, 0] * frac
    pz = eye[:, None, None, 1] + delta[..., None, 1] * frac
    ray_h = CAMERA_HEIGHT + (obj_center[None, :, None, 1] - CAMERA_HEIGHT) * frac
    ci = np.clip(np.rint(pz / GRID_SIZE).astype(np.int64), 0, H - 1)
    cj = np.clip(np.rint(px / GRID_SIZE).astype(np.int64), 0, W - 1)
    blocked = (block_height[ci, cj] > ray_h) & (t[None, None, :] < stop[..., None])
    return ~blocked.any(-1)


def object_visibility(poses: np.ndarray, cells: np.ndarray, los: np.ndarray,
                      obj_center: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per state and object: (in_view & line of sight) (S, K), horizontal distance
    (S, K), camera coordinates (S, K, 3). `los` is (M, K) from line_of_sight."""
    cam = to_camera(poses, obj_center)
    d = np.hypot(obj_center[None, :, 0] - poses[:, None, 0],
                 obj_center[None, :, 2] - poses[:, None, 1])
    seen = in_view(cam) & np.repeat(los, STATES_PER_CELL, axis=0)
    return seen, d, cam


def category_visible(seen: np.ndarray, dist: np.ndarray, obj_category: np.ndarray,
                     num_categories: int) -> np.ndarray:
    """(S, K) seen, (S, K) distance -> (S, C) bool: some instance of c is in view,
    unoccluded and within VISIBILITY_DISTANCE (horizontal)."""
    close = seen & (dist <= VISIBILITY_DISTANCE)
    out = np.zeros((seen.shape[0], num_categories), bool)
    for c in np.unique(obj_category):
        out[:, c] = close[:, obj_category == c].any(1)
    return out
