"""Import the authors' offline AI2-THOR data (FloorPlanN folders) into a SceneSet.

Two passes: (1) read and cross-check every scene's JSON files and hdf5 headers, which
fixes N, S (the largest scene) and the feature widths; (2) allocate the padded float16
arrays once and stream the features into them state by state. Expert tables are ours
(scenes.expert.expert_tables); optimal_action.json, when present, is only compared.

Imported SceneSets hold the features themselves (bases None): appearance (N, S, C, d),
global_feat (N, S, 7, 7, G), both float16. Poses keep the authors' metres (possibly
negative) so that state_key(pose) reproduces their keys; states are ordered by grid row
(z), column (x), heading, horizon, valid states first, padding as in every SceneSet.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from orgnav_jax.constants import NUM_ACTIONS, NUM_CATEGORIES
from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.builder import (
    EXPERT_CHUNK, FORMAT_NAME, FORMAT_VERSION, STORE_DTYPE, valid_targets,
)
from orgnav_jax.scenes.expert import expert_tables
from orgnav_jax.scenes.offline import files
from orgnav_jax.scenes.offline.features_io import (
    FeatureLayout, detection_rows, find_detection_file, inspect_scene, stream_scene,
)
from orgnav_jax.scenes.offline.optimal import compare_optimal
from orgnav_jax.scenes.offline.reader import SceneGraph, read_scene
from orgnav_jax.scenes.offline.splits import assign_splits
from orgnav_jax.scenes.offline.validate import SCENE_NAME, OfflineFormatError, examples
from orgnav_jax.scenes.sceneset import NO_ACTION, UNREACHABLE, SceneSet
from orgnav_jax.scenes.storage import is_scene_set, save


def scene_folders(offline_dir: str | os.PathLike, names=None) -> list[Path]:
    """The FloorPlanN folders under `offline_dir` (all, or those named), or the folder
    itself when it is one scene."""
    root = Path(offline_dir)
    if not root.is_dir():
        raise OfflineFormatError(f"{root}: offline data directory does not exist")
    if (root / files.GRAPH_FILE).is_file():
        found = {root.name: root}
    else:
        found = {p.name: p for p in root.iterdir() if p.is_dir() and SCENE_NAME.match(p.name)}
    if names:
        missing = [n for n in names if n not in found]
        if missing:
            raise OfflineFormatError(f"{root}: no scene folder(s) {examples(missing)} "
                                     f"(found {len(found)}: {examples(found)})")
        return [found[n] for n in names]
    if not found:
        other = [p.name for p in root.iterdir() if (p / files.GRAPH_FILE).is_file()]
        hint = (f"; folders {examples(other)} hold {files.GRAPH_FILE}: give their splits "
                "and room types with --splits FILE.json") if other else ""
        raise OfflineFormatError(f"{root}: no FloorPlanN scene folders (each holding "
                                 f"{files.GRAPH_FILE}, {files.GRID_FILE}, ...){hint}")
    return sorted(found.values(), key=lambda p: p.name)


def _layout(graphs, det_paths, detection_rows_arg) -> FeatureLayout:
    layout = None
    for g, det in zip(graphs, det_paths):
        gshape, dshape = inspect_scene(g.folder, g.keys, det)
        if layout is None:
            rows = detection_rows(detection_rows_arg, dshape[0], str(det))
            layout = FeatureLayout(gshape, dshape, rows)
        elif (gshape, dshape) != (layout.global_shape, layout.det_shape):
            raise OfflineFormatError(
                f"{g.folder}: feature shapes resnet {gshape}, detection {dshape} differ from "
                f"{graphs[0].folder.name}'s {layout.global_shape}, {layout.det_shape}")
    return layout


def _expert(next_state, visible, valid):
    N, S, C = visible.shape
    dist = np.full((N, S, C), UNREACHABLE, np.int16)
    action = np.full((N, S, C), NO_ACTION, np.int8)
    for lo in range(0, N, EXPERT_CHUNK):
        hi = min(lo + EXPERT_CHUNK, N)
        idx = np.arange(lo, lo + EXPERT_CHUNK) % N  # pad the last chunk: one compile
        d, a = expert_tables(jnp.asarray(next_state[idx]), jnp.asarray(visible[idx]),
                             jnp.asarray(valid[idx]))
        dist[lo:hi], action[lo:hi] = np.asarray(d)[:hi - lo], np.asarray(a)[:hi - lo]
    return dist, action


def import_offline(offline_dir: str | os.PathLike, scenes=None, *, detection_file=None,
                   detection_rows=None, unknown_types: str = "ignore",
                   unmatched_edges: str = "error", progress: bool = False,
                   splits=None, only_listed: bool = False) -> tuple[SceneSet, dict]:
    """Offline scene folders -> (SceneSet of numpy arrays, report).

    scenes: folder names to import (default all FloorPlanN under offline_dir).
    splits: a JSON file, room (folder) name -> split (or {"split", "room_type"}), for
      rooms that do not follow the authors' FloorPlan numbering (offline/splits.py);
      only_listed: import only the rooms it names (default: it must name every one).
    detection_file: detection hdf5 name (default: first of files.DETECTION_FILES found).
    detection_rows: which rows are the 22 categories (features_io.detection_rows); needed
      when the detection datasets do not have exactly 22 rows.
    unknown_types: 'ignore' (default; AI2-THOR visibility maps list every object type,
      the ignored type names are reported) or 'error' for object types outside the 22.
    unmatched_edges: 'error' (default) or 'ignore' for graph edges matching no action.
    The report holds, per scene, states, edges, ignored items and, when
    optimal_action.json is present, the comparison with our expert (optimal.py).
    """
    for name, value, allowed in (("unknown_types", unknown_types, ("ignore", "error")),
                                 ("unmatched_edges", unmatched_edges, ("error", "ignore"))):
        if value not in allowed:
            raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
    t0 = time.perf_counter()
    if splits is None:
        folders, assigned, custom = scene_folders(offline_dir, scenes), {}, {}
    else:
        folders, assigned, custom = assign_splits(offline_dir, splits, scenes, only_listed)
    with tqdm(folders, desc="scene graphs", disable=not progress) as bar:  # closed on errors
        graphs: list[SceneGraph] = [read_scene(f, unknown_types, unmatched_edges,
                                               assigned.get(f.name)) for f in bar]
    graphs.sort(key=lambda g: (g.room_type, g.split, g.number))
    numbers = [g.number for g in graphs]
    if len(set(numbers)) != len(numbers):
        dup = {f"FloorPlan{n}" for n in numbers if numbers.count(n) > 1}
        raise OfflineFormatError(f"{offline_dir}: scene(s) {examples(dup)} appear twice "
                                 "(FloorPlanN and FloorPlanN_physics?)")
    det_paths = [find_detection_file(g.folder, detection_file) for g in graphs]
    layout = _layout(graphs, det_paths, detection_rows)
    t_json = time.perf_counter() - t0

    N, S, C = len(graphs), max(len(g.keys) for g in graphs), NUM_CATEGORIES
    d, G = layout.appearance_dim, layout.global_dim
    next_state = np.tile(np.arange(S, dtype=np.int32)[None, :, None], (N, 1, NUM_ACTIONS))
    valid = np.zeros((N, S), bool)
    pose = np.zeros((N, S, 4), np.float32)
    visible = np.zeros((N, S, C), bool)
    glob = np.zeros((N, S, 7, 7, G), STORE_DTYPE)
    appearance = np.zeros((N, S, C, d), STORE_DTYPE)
    det_box = np.zeros((N, S, C, 4), STORE_DTYPE)
    det_conf = np.zeros((N, S, C), STORE_DTYPE)
    t1 = time.perf_counter()
    with tqdm(list(zip(graphs, det_paths)), desc="features", disable=not progress) as bar:
        for n, (g, det) in enumerate(bar):
            k = len(g.keys)
            next_state[n, :k], valid[n, :k] = g.next_state, True
            pose[n, :k], visible[n, :k] = g.pose, g.visible
            stream_scene(g.folder, g.keys, det, layout, glob[n], appearance[n], det_box[n],
                         det_conf[n])
    t_feat = time.perf_counter() - t1

    t2 = time.perf_counter()
    dist, action = _expert(next_state, visible, valid)
    t_expert = time.perf_counter() - t2
    room_type = np.array([g.room_type for g in graphs], np.int32)
    present = np.stack([g.present for g in graphs])
    per_scene = []
    for n, g in enumerate(graphs):
        k = len(g.keys)
        rep = dict(g.report, detection_file=det_paths[n].name)
        if g.authors_action is not None:
            rep["optimal_action"] = compare_optimal(g.authors_action, next_state[n, :k],
                                                    dist[n, :k], action[n, :k], g.keys)
        per_scene.append(rep)
    out = SceneSet(
        next_state=next_state, state_valid=valid, pose=pose, visible=visible, present=present,
        targets=valid_targets(room_type, present, dist), state_count=valid.sum(1, dtype=np.int32),
        dist=dist, expert_action=action, det_box=det_box, det_conf=det_conf,
        appearance=appearance, global_feat=glob, room_type=room_type,
        scene_id=np.array(numbers, np.int32), split=np.array([g.split for g in graphs], np.int32),
        info=(("format", FORMAT_NAME), ("version", FORMAT_VERSION), ("preset", "offline"),
              ("source", str(Path(offline_dir).resolve())),
              ("detection_file", det_paths[0].name)))
    if splits is not None:  # custom names first: validate's messages use scene_names
        out = out.replace(info=out.info + (("splits", str(Path(splits).resolve())),) + (
            (("room_names", tuple(custom.values())), ("room_name_ids", tuple(custom)))
            if custom else ()))
    out.validate(str(offline_dir))
    opt = [r["optimal_action"] for r in per_scene if "optimal_action" in r]
    report = {
        "scenes": per_scene, "num_scenes": N, "states": int(valid.sum()), "padded_states": S,
        "global_dim": G, "appearance_dim": d, "detection_rows": int(layout.det_shape[0]),
        "seconds": {"json": round(t_json, 3), "features": round(t_feat, 3),
                    "expert": round(t_expert, 3)},
        "optimal_action": {k: sum(o[k] for o in opt) for k in
                           ("compared", "exact", "on_shortest_path", "mismatches",
                            "no_path_here")} if opt else None,
    }
    return out, report


def import_to(offline_dir: str | os.PathLike, out: str | os.PathLike, **kwargs
              ) -> tuple[SceneSet, dict]:
    """import_offline, then scenes.save to `out` (loads with scenes.load(out)).

    `out` must be absent, empty or a SceneSet (checked before importing); anything else
    is refused and left untouched."""
    check_output_dir(out, is_scene_set, "a SceneSet")
    scenes, report = import_offline(offline_dir, **kwargs)
    save(scenes, out, validate=False)  # import_offline validated it
    return scenes, report


def format_report(report: dict) -> str:
    """A few human lines about an import."""
    s = report["seconds"]
    lines = [(f"imported {report['num_scenes']} scene(s), {report['states']} states "
              f"(S padded to {report['padded_states']}), global 7x7x{report['global_dim']}, "
              f"appearance {NUM_CATEGORIES}x{report['appearance_dim']} from "
              f"{report['detection_rows']}-row detections; json {s['json']:.1f} s, features "
              f"{s['features']:.1f} s, expert {s['expert']:.1f} s")]
    for r in report["scenes"]:
        extra = []
        if r["ignored_edges"]:
            extra.append(f"{r['ignored_edges']} edges matching no action ignored")
        if r.get("ignored_types"):
            extra.append(f"{len(r['ignored_types'])} object types outside the 22 ignored")
        if r["grid_points_without_states"]:
            extra.append(f"{r['grid_points_without_states']} grid points without states")
        o = r.get("optimal_action")
        if o:
            extra.append(f"optimal_action: {o['mismatches']} of {o['compared']} not on a "
                         f"shortest path ({o['exact']} identical, {o['no_path_here']} where we "
                         "find no path)")
        if extra:
            lines.append(f"  {r['scene']}: " + "; ".join(extra))
    return "\n".join(lines)
