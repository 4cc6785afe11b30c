"""Write any SceneSet in the authors' offline format, one FloorPlanN folder per scene,
so that their PyTorch code can run on exactly our rooms.

Per scene: graph.json (node_link_data; one link per successful action, failed moves are
absent as in the release), grid.json (reachable points, y = files.GRID_Y),
visible_object_map_1.5.json, optimal_action.json (our expert; only where a path
exists), resnet18_featuremap.hdf5 ((1, G, 7, 7) per state) and
fasterrcnn_features_22cls.hdf5 ((22, d + 5) per state), features decoded at the
SceneSet's widths with sceneset/features.py decode_*.

Output folder: absent, empty, or an export of ours (is_offline_export: the marker file
orgnav_export.json, FloorPlanN folders holding only the files above, and the episode
files the CLI writes); anything else is refused and left untouched. Scene folders of an
earlier export that are not in this one are kept (exports can be made piecewise with
--scenes); a re-exported scene replaces its folder, deleting only the files listed here.

Object ids: a SceneSet keeps per-category visibility, not object instances, so each
present category gets ONE synthetic objectId 'Type|+x.xx|+01.00|+z.zz' placed at the
mean position of the states that see it (the room's centre if none does); its state
list is exactly visible[:, c]. Categories present but never visible get an empty list.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path
from types import SimpleNamespace

import h5py
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from orgnav_jax.constants import CATEGORIES, DONE, SPLITS
from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.sceneset.features import decode_appearance, decode_global
from orgnav_jax.scenes.sceneset.keys import scene_state_keys
from orgnav_jax.scenes.offline import files
from orgnav_jax.scenes.offline.validate import SCENE_NAME
from orgnav_jax.scenes.sceneset.fields import UNREACHABLE
from orgnav_jax.scenes.sceneset.sceneset import SceneSet

CHUNK = 256  # states decoded per jitted call (fixed: one compile per feature width)
OBJECT_Y = 1.0
MARKER_FILE = "orgnav_export.json"  # marks a folder written by export_offline
MARKER = {"format": "orgnav_jax.offline_export", "version": 1}
SCENE_FILES = frozenset((files.GRAPH_FILE, files.GRID_FILE, files.VISIBLE_FILES[0],
                         files.OPTIMAL_FILE, files.RESNET_FILE, files.EXPORT_DETECTION_FILE))
EPISODES_DIR = "episodes"  # the CLI's --episodes-per-type files: <split>.json / .pkl
EPISODE_FILES = frozenset(f"{split}{suffix}{tmp}" for split in SPLITS
                          for suffix in (".json", ".pkl") for tmp in ("", ".tmp"))


def _only_files(folder: Path, names) -> bool:
    return all(p.name in names and p.is_file() and not p.is_symlink()
               for p in folder.iterdir())


def is_offline_export(path: str | os.PathLike) -> bool:
    """True if `path` holds an export of ours and nothing else: the marker file, scene
    folders FloorPlanN (or their temporary .FloorPlanN.tmp) with only the exporter's
    files, and an `episodes` folder with only the CLI's episode files."""
    path = Path(path)
    try:
        if json.loads((path / MARKER_FILE).read_text()) != MARKER:
            return False
        for p in path.iterdir():
            if p.is_symlink():
                return False
            if p.name == MARKER_FILE and p.is_file():
                continue
            if p.name == EPISODES_DIR and p.is_dir():
                if not _only_files(p, EPISODE_FILES):
                    return False
                continue
            name = p.name[1:-4] if p.name.startswith(".") and p.name.endswith(".tmp") else p.name
            if not (SCENE_NAME.match(name) and p.is_dir() and _only_files(p, SCENE_FILES)):
                return False
    except (OSError, ValueError, RecursionError):
        return False
    return True


def check_export_dir(out_dir: str | os.PathLike, option: str = "--out") -> None:
    """Refuse (FileExistsError) an output folder that is a file or non-empty and not an
    export of ours."""
    check_output_dir(out_dir, is_offline_export, "an offline export of orgnav_jax "
                     f"(with {MARKER_FILE})", option=option)


def _remove_scene_folder(folder: Path) -> None:
    """Delete the exporter's files in `folder`, then the folder; anything else there
    makes it an error (nothing else is deleted)."""
    for p in folder.iterdir():
        if p.name in SCENE_FILES and p.is_file() and not p.is_symlink():
            p.unlink()
    try:
        folder.rmdir()
    except OSError:
        raise FileExistsError(f"{folder}: holds files the exporter did not write; it is left "
                              "untouched: choose another --out") from None


def object_ids(pose: np.ndarray, visible: np.ndarray, present: np.ndarray) -> dict[int, str]:
    """One scene's valid states: (S, 4) poses, (S, C) visible, (C,) present ->
    {category: synthetic objectId}."""
    out = {}
    for c in np.flatnonzero(present):
        where = pose[visible[:, c], :2] if visible[:, c].any() else pose[:, :2]
        x, z = where.mean(0)
        out[int(c)] = f"{CATEGORIES[c]}|{x:+06.2f}|{OBJECT_Y:+06.2f}|{z:+06.2f}"
    return out


@jax.jit
def _decode(bases: dict, glob_code, app_code, conf):
    ns = SimpleNamespace(**bases)
    return decode_global(ns, glob_code), decode_appearance(ns, app_code, conf)


def decoded_features(scenes: SceneSet, n: int, chunk: int = CHUNK):
    """Yield (lo, hi, global (k, 7, 7, G) float32, appearance (k, C, d) float32) for the
    valid states lo..hi of scene n, decoded as the model sees them."""
    bases = {k: None if getattr(scenes, k) is None else jnp.asarray(getattr(scenes, k))
             for k in ("global_basis", "appearance_basis", "appearance_proto",
                       "global_scale", "appearance_scale")}
    rows = scenes.state_slice(n)
    count = rows.stop - rows.start
    glob, app = scenes.global_feat[rows], scenes.appearance[rows]
    conf = scenes.det_conf[rows]
    for lo in range(0, count, chunk):
        hi = min(lo + chunk, count)
        idx = np.minimum(np.arange(lo, lo + chunk), count - 1)  # pad: fixed shape
        g, a = _decode(bases, jnp.asarray(glob[idx]), jnp.asarray(app[idx]),
                       jnp.asarray(conf[idx], jnp.float32))
        yield lo, hi, np.asarray(g)[:hi - lo], np.asarray(a)[:hi - lo]


def _dump(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, separators=(",", ":")))


def _write_json_files(folder: Path, keys, pose, nxt, visible, present, dist, action) -> None:
    S = len(keys)
    src, act = np.nonzero(nxt[:, :DONE] != np.arange(S)[:, None])
    _dump(folder / files.GRAPH_FILE, {
        "directed": True, "multigraph": False, "graph": {},
        "nodes": [{"id": k} for k in keys],
        "links": [{"source": keys[s], "target": keys[nxt[s, a]]} for s, a in zip(src, act)]})
    points = sorted({(round(float(x), 2), round(float(z), 2)) for x, z in pose[:, :2]})
    _dump(folder / files.GRID_FILE, [{"x": x, "y": files.GRID_Y, "z": z} for x, z in points])
    ids = object_ids(pose, visible, present)
    _dump(folder / files.VISIBLE_FILES[0],
          {oid: [keys[s] for s in np.flatnonzero(visible[:, c])] for c, oid in ids.items()})
    ok = dist < UNREACHABLE
    _dump(folder / files.OPTIMAL_FILE,
          {k: {CATEGORIES[c]: int(action[s, c]) for c in np.flatnonzero(ok[s])}
           for s, k in enumerate(keys)})


def export_scene(scenes: SceneSet, n: int, folder: Path, hdf5_dtype: str = "float32") -> int:
    """Write scene n into `folder` (created). Returns its number of states."""
    rows = scenes.state_slice(n)
    count = rows.stop - rows.start
    pose = np.asarray(scenes.pose[rows])
    keys = scene_state_keys(pose, count)
    _write_json_files(folder, keys, pose, np.asarray(scenes.next_state[rows]) - rows.start,
                      np.asarray(scenes.visible[rows]), np.asarray(scenes.present[n]),
                      np.asarray(scenes.dist[rows]), np.asarray(scenes.expert_action[rows]))
    box = np.asarray(scenes.det_box[rows], np.float32)
    conf = np.asarray(scenes.det_conf[rows], np.float32)
    with h5py.File(folder / files.RESNET_FILE, "w") as fg, \
            h5py.File(folder / files.EXPORT_DETECTION_FILE, "w") as fd:
        for lo, hi, glob, app in decoded_features(scenes, n):
            glob = glob.transpose(0, 3, 1, 2)[:, None].astype(hdf5_dtype)  # (k, 1, G, 7, 7)
            det = np.concatenate([app, box[lo:hi], conf[lo:hi, :, None]], -1).astype(hdf5_dtype)
            for i in range(hi - lo):
                fg.create_dataset(keys[lo + i], data=glob[i])
                fd.create_dataset(keys[lo + i], data=det[i])
    return count


def export_offline(scenes: SceneSet, out_dir: str | os.PathLike, *, hdf5_dtype: str = "float32",
                   progress: bool = False) -> dict:
    """Write every scene of `scenes` as out_dir/FloorPlanN (each replaced atomically).
    Returns {"scenes", "states", "seconds", "bytes"}.

    out_dir must be absent, empty or an earlier export (is_offline_export); anything else
    is refused (FileExistsError) and left untouched."""
    out_dir = Path(out_dir)
    check_export_dir(out_dir, option="output")
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / MARKER_FILE).write_text(json.dumps(MARKER) + "\n")
    t0, states = time.perf_counter(), 0
    with tqdm(scenes.scene_names, desc="export", disable=not progress) as bar:
        for n, name in enumerate(bar):
            final, tmp = out_dir / name, out_dir / f".{name}.tmp"
            if tmp.exists():
                _remove_scene_folder(tmp)  # left by an interrupted export of ours
            tmp.mkdir()
            try:
                states += export_scene(scenes, n, tmp, hdf5_dtype)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)  # made by this call
                raise
            if final.exists():
                _remove_scene_folder(final)
            tmp.rename(final)
    size = sum(f.stat().st_size for d in scenes.scene_names for f in (out_dir / d).iterdir())
    return {"scenes": scenes.num_scenes, "states": states,
            "seconds": round(time.perf_counter() - t0, 3), "bytes": size}
