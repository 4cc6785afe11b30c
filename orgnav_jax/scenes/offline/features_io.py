"""Stream an offline scene's features from HDF5 into preallocated 16-bit arrays.

resnet18_featuremap.hdf5: one dataset per state key, (1, G, 7, 7) channels-first (or
(G, 7, 7)); stored transposed as (7, 7, G). Detection hdf5: one dataset per state key,
(R, d + 5) = appearance d, box x1 y1 x2 y2, confidence; R = 22 rows in the 22-category
order, or any other R (e.g. the release's 60 classes) with an explicit row selection.
States are read one at a time into a small float32 buffer and written into the caller's
float16 arrays, so memory is bounded by the output, never by a float32 copy of it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np

from orgnav_jax.constants import CATEGORIES, FEATURE_GRID, NUM_CATEGORIES
from orgnav_jax.scenes.offline import files
from orgnav_jax.scenes.offline.validate import OfflineFormatError, check_same_keys, examples

ALL = h5py.h5s.ALL
BOX_CONF = 5  # columns after the appearance feature: x1, y1, x2, y2, confidence
F16_MAX = float(np.finfo(np.float16).max)  # 65504


@dataclasses.dataclass(frozen=True)
class FeatureLayout:
    """Shapes shared by every scene of an import."""
    global_shape: tuple[int, ...]  # per-state resnet dataset shape, (1, G, 7, 7) or (G, 7, 7)
    det_shape: tuple[int, int]     # per-state detection dataset shape (R, d + 5)
    rows: np.ndarray               # (22,) row of the detection dataset for each category

    @property
    def global_dim(self) -> int:
        return int(self.global_shape[-3])

    @property
    def appearance_dim(self) -> int:
        return int(self.det_shape[1] - BOX_CONF)


def find_detection_file(folder: Path, name: str | None = None) -> Path:
    """The detection hdf5 of a scene: `name` if given, else the first of
    files.DETECTION_FILES that exists."""
    names = (name,) if name else files.DETECTION_FILES
    for n in names:
        if (folder / n).is_file():
            return folder / n
    raise OfflineFormatError(f"{folder}: missing detection hdf5 (tried {', '.join(names)}); "
                             "name it with detection_file= / --detection-file")


def detection_rows(selection, num_rows: int, source: str) -> np.ndarray:
    """(22,) row indices of the 22 categories in a detection dataset of `num_rows` rows.

    selection: None (the file must have 22 rows, in the 22-category order); a sequence of
    22 ints (the row of each category, in constants.CATEGORIES order); or a sequence of
    `num_rows` class names, the file's row order (e.g. for the release's 60-class files,
    the list AI2THOR_TARGET_CLASSES[60] of its datasets/constants.py).
    """
    if selection is None:
        if num_rows == NUM_CATEGORIES:
            return np.arange(NUM_CATEGORIES)
        raise OfflineFormatError(
            f"{source}: detection datasets have {num_rows} rows, not 22, and the order of "
            f"those {num_rows} classes is not part of the format; say which rows hold the 22 "
            "categories: detection_rows=<list of the file's class names in row order> "
            "(CLI --detection-classes FILE.json) or <22 row indices> (CLI --detection-rows)")
    sel = list(selection)
    if sel and all(isinstance(s, str) for s in sel):
        if len(sel) != num_rows:
            raise OfflineFormatError(f"{source}: {len(sel)} class names given for detection "
                                     f"datasets of {num_rows} rows")
        missing = [c for c in CATEGORIES if c not in sel]
        if missing:
            raise OfflineFormatError(f"{source}: the detection class list lacks categories "
                                     f"{examples(missing)}")
        return np.array([sel.index(c) for c in CATEGORIES])
    try:
        rows = np.array([int(r) for r in sel])
    except (TypeError, ValueError):
        raise OfflineFormatError(f"{source}: detection rows {sel!r} must be 22 row indices "
                                 f"or {num_rows} class names") from None
    if rows.shape != (NUM_CATEGORIES,) or rows.min() < 0 or rows.max() >= num_rows:
        raise OfflineFormatError(f"{source}: detection rows must be 22 indices in "
                                 f"[0, {num_rows}), one per category, got {sel!r}")
    return rows


def _open(path: Path) -> h5py.File:
    try:
        return h5py.File(path, "r")
    except OSError as e:
        raise OfflineFormatError(f"{path}: cannot open as HDF5 ({e})") from None


def _dataset(f: h5py.File, key: str, path: Path, shape: tuple):
    """Low-level handle of dataset `key` (8x faster than f[key]), its shape checked."""
    try:
        ds = h5py.h5d.open(f.id, key.encode())
    except (KeyError, ValueError, OSError):  # a group, or absent (keys were checked)
        raise OfflineFormatError(f"{path}: entry {key!r} is not a dataset") from None
    if tuple(ds.shape) != tuple(shape):
        raise OfflineFormatError(f"{path}: dataset {key!r} has shape {tuple(ds.shape)}, "
                                 f"expected {tuple(shape)} like the other states")
    return ds


def inspect_scene(folder: Path, keys: list[str], det_path: Path) -> tuple[tuple, tuple]:
    """Check both hdf5 files hold exactly the graph's state keys; return the shape of one
    resnet and one detection dataset (every dataset is checked while streaming)."""
    graph = str(folder / files.GRAPH_FILE)
    shapes = []
    for path, want in ((folder / files.RESNET_FILE, "resnet"), (det_path, "detection")):
        if not path.is_file():
            raise OfflineFormatError(f"{path}: missing file ({want} features, one dataset "
                                     "per state key)")
        with _open(path) as f:
            check_same_keys(str(path), f.keys(), graph, keys)
            shape = tuple(f[keys[0]].shape) if isinstance(f[keys[0]], h5py.Dataset) else ()
        shapes.append(shape)
    g, d = shapes
    if not ((len(g) == 4 and g[0] == 1 and g[2:] == (FEATURE_GRID,) * 2)
            or (len(g) == 3 and g[1:] == (FEATURE_GRID,) * 2)):
        raise OfflineFormatError(f"{folder / files.RESNET_FILE}: dataset {keys[0]!r} has shape "
                                 f"{g}, expected (1, G, 7, 7) (G = 512 for ResNet-18)")
    if g[-3] < 1:
        raise OfflineFormatError(f"{folder / files.RESNET_FILE}: dataset {keys[0]!r} has shape "
                                 f"{g}: 0 feature channels, expected G >= 1 (512 for "
                                 "ResNet-18)")
    if len(d) != 2 or d[1] <= BOX_CONF:
        raise OfflineFormatError(f"{det_path}: dataset {keys[0]!r} has shape {d}, expected "
                                 "(22, 517): rows of 512 appearance, 4 box, 1 confidence")
    return g, d


def check_finite(values: np.ndarray, path: Path, key: str, rows=None) -> None:
    """A dataset's values (float32) must be finite and fit the float16 the SceneSet
    stores (|x| <= 65504); the error names the file, the dataset and, for detections,
    the row (category) and column."""
    peak = np.max(np.abs(values)) if values.size else 0.0  # NaN propagates
    if np.isfinite(peak) and peak <= F16_MAX:
        return
    bad = ~np.isfinite(values) | (np.abs(values) > F16_MAX)
    index = np.unravel_index(int(np.argmax(bad)), values.shape)
    value = float(values[index])
    what = "NaN" if np.isnan(value) else ("Inf" if np.isinf(value) else
                                          f"{value:g}, beyond the float16 range")
    where = ""
    if rows is not None:  # detection (22, d + 5): name the category row and the column
        r, col = (int(i) for i in index)
        d = values.shape[1] - BOX_CONF
        part = ("appearance feature" if col < d else
                "box" if col < d + 4 else "confidence")
        where = f" row {int(rows[r])} ({CATEGORIES[r]}) {part}"
    raise OfflineFormatError(f"{path} dataset {key!r}:{where} holds {what}; expected finite "
                             f"features (|x| <= {F16_MAX:g}, stored as float16)")


def stream_scene(folder: Path, keys: list[str], det_path: Path, layout: FeatureLayout,
                 glob: np.ndarray, appearance: np.ndarray, det_box: np.ndarray,
                 det_conf: np.ndarray) -> None:
    """Fill glob (S, 7, 7, G), appearance (S, C, d), det_box (S, C, 4), det_conf (S, C)
    (16-bit views into the stacked SceneSet arrays) for states `keys`, in order."""
    d = layout.appearance_dim
    gbuf = np.empty(layout.global_shape, np.float32)
    dbuf = np.empty(layout.det_shape, np.float32)
    rows = layout.rows
    resnet_path = folder / files.RESNET_FILE
    with _open(resnet_path) as fg, _open(det_path) as fd:
        for i, key in enumerate(keys):
            _dataset(fg, key, resnet_path, layout.global_shape).read(ALL, ALL, gbuf)
            check_finite(gbuf, resnet_path, key)
            glob[i] = gbuf.reshape(layout.global_shape[-3:]).transpose(1, 2, 0)
            _dataset(fd, key, det_path, layout.det_shape).read(ALL, ALL, dbuf)
            sel = dbuf[rows]
            check_finite(sel, det_path, key, rows)
            appearance[i] = sel[:, :d]
            det_box[i] = sel[:, d:d + 4]
            det_conf[i] = sel[:, d + 4]
