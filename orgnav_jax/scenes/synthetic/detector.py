"""A seeded model of an object detector: boxes, confidences, appearance codes (numpy).

Range grows with object size (a Fridge is found from across the room, a CellPhone only
up close), misses grow with distance, and a few false positives appear everywhere.
Appearance codes are low-dimensional; `features.decode_appearance` turns them into
d-wide features (class prototype + view-dependent noise) inside jit.
"""

from __future__ import annotations

import numpy as np

from orgnav_jax.constants import CATEGORIES, IMAGE_SIZE, NUM_CATEGORIES
from orgnav_jax.scenes.synthetic.catalog import OBJECTS
from orgnav_jax.scenes.synthetic.geometry import to_camera
from orgnav_jax.scenes.synthetic.perception import Perception

DETECT_RANGE = np.array([OBJECTS[c].detect_range for c in CATEGORIES], np.float32)
MAX_DETECT_DISTANCE = 6.5      # metres; beyond this nothing is detected
RANGE_SOFTNESS = 0.3           # metres: how quickly recall falls off past the range
APPEARANCE_CODE_DIM = 8        # stored code width per (state, category)

_BOX_CORNERS = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])


def project_boxes(poses: np.ndarray, obj_center: np.ndarray, obj_size: np.ndarray,
                  obj_height: np.ndarray) -> np.ndarray:
    """Pixel boxes (x1, y1, x2, y2) of each object's 3-D box in a 300x300 pinhole image.

    poses (S, 4); objects (K, 3) centres, (K,) sizes and heights -> (S, K, 4) float32,
    clipped to the image (corners behind the camera are pushed to 5 cm in front).
    """
    ext = np.stack([obj_size, obj_height, obj_size], 1)                 # (K, 3)
    corners = obj_center[:, None, :] + _BOX_CORNERS[None] * ext[:, None]  # (K, 8, 3)
    cam = to_camera(poses, corners.reshape(-1, 3)).reshape(len(poses), -1, 8, 3)
    z = np.maximum(cam[..., 2], 0.05)
    half = IMAGE_SIZE / 2
    px = half + half * cam[..., 0] / z
    py = half - half * cam[..., 1] / z
    box = np.stack([px.min(-1), py.min(-1), px.max(-1), py.max(-1)], -1)
    return np.clip(box, 0, IMAGE_SIZE).astype(np.float32)


def detect(rng: np.random.Generator, seen: np.ndarray, dist: np.ndarray, boxes: np.ndarray,
           obj_category: np.ndarray, p: Perception = Perception()
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Run the detector model on every state.

    seen, dist: (S, K) from geometry.object_visibility; boxes: (S, K, 4); p: the
    detector's knobs (peak recall, range, smallest box, false positives, confidence and
    appearance noise; perception.py).
    Returns det_box (S, C, 4) float32 pixels, det_conf (S, C) float32 (0 = none),
    appearance code (S, C, APPEARANCE_CODE_DIM) float32 (0 where nothing detected).
    """
    S, K = seen.shape
    rng_range = DETECT_RANGE[obj_category][None] * p.detect_range_scale     # (1, K)
    recall = p.peak_recall / (1 + np.exp((dist - rng_range) / RANGE_SOFTNESS))
    area = (boxes[..., 2] - boxes[..., 0]) * (boxes[..., 3] - boxes[..., 1])
    hit = (seen & (dist <= MAX_DETECT_DISTANCE) & (area >= p.min_box_area)
           & (rng.random((S, K)) < recall))
    conf = np.clip(0.55 + 0.4 * (1 - dist / rng_range)
                   + rng.normal(0, p.confidence_noise, (S, K)), 0.05, 0.99)
    conf = np.where(hit, conf, 0.0)
    instance_code = rng.normal(0, 1, (K, APPEARANCE_CODE_DIM))
    view_noise = rng.normal(0, 1, (S, K, APPEARANCE_CODE_DIM))

    det_box = np.zeros((S, NUM_CATEGORIES, 4), np.float32)
    det_conf = np.zeros((S, NUM_CATEGORIES), np.float32)
    code = np.zeros((S, NUM_CATEGORIES, APPEARANCE_CODE_DIM), np.float32)
    for c in np.unique(obj_category):
        ks = np.flatnonzero(obj_category == c)
        best = ks[np.argmax(conf[:, ks], axis=1)]                            # (S,)
        s = np.arange(S)
        det_conf[:, c] = conf[s, best]
        det_box[:, c] = boxes[s, best]
        code[:, c] = 0.7 * instance_code[best] + p.appearance_noise * view_noise[s, best]

    # False positives: a low-confidence box of a category that was not detected.
    fp = (rng.random((S, NUM_CATEGORIES)) < p.false_positive_rate) & (det_conf == 0)
    n = int(fp.sum())
    centre = rng.uniform(20, IMAGE_SIZE - 20, (n, 2))
    half = rng.uniform(5, 30, (n, 2))
    det_box[fp] = np.clip(np.concatenate([centre - half, centre + half], 1), 0, IMAGE_SIZE)
    det_conf[fp] = rng.uniform(0.05, p.fp_confidence_max, n)
    code[fp] = 1.5 * rng.normal(0, 1, (n, APPEARANCE_CODE_DIM))
    det_box[det_conf == 0] = 0.0
    code[det_conf == 0] = 0.0
    return det_box, det_conf.astype(np.float32), code
