"""Import the authors' offline AI2-THOR data (FloorPlanN folders) into a SceneSet.

Two passes: (1) read and cross-check every scene's JSON files and hdf5 headers, which
fixes N, the state counts and the feature widths; (2) hand the rooms to the SceneSet
assembly (sceneset/assemble.py), which allocates the flat float16 arrays (T states of
all rooms, no padding) once; each room's features are streamed into its rows state by
state. Expert tables are ours (sceneset/expert.py); optimal_action.json, when present,
is only compared.

Imported SceneSets hold the features themselves (bases None): appearance (T, C, d),
global_feat (T, 7, 7, G), both float16 (sceneset/quantize.py makes them int8 on request).
Poses keep the authors' metres (possibly negative) so that state_key(pose) reproduces
their keys; states are ordered by grid row
(z), column (x), heading, horizon within each room; rooms are stored grouped by split
(assemble.py).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from tqdm.auto import tqdm

from orgnav_jax.constants import NUM_CATEGORIES
from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.offline import files
from orgnav_jax.scenes.offline.features_io import (
    FeatureLayout, detection_rows, find_detection_file, inspect_scene, stream_scene,
)
from orgnav_jax.scenes.offline.optimal import compare_optimal
from orgnav_jax.scenes.offline.reader import SceneGraph, read_scene
from orgnav_jax.scenes.offline.splits import assign_splits
from orgnav_jax.scenes.offline.validate import SCENE_NAME, OfflineFormatError, examples
from orgnav_jax.scenes.sceneset.assemble import SourceRoom, assemble
from orgnav_jax.scenes.sceneset.fields import FORMAT_INFO
from orgnav_jax.scenes.sceneset.quantize import FEATURE_DTYPES, with_features
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.sceneset.storage import is_scene_set, save


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


def _room(g: SceneGraph, det: Path, layout: FeatureLayout, clock: dict) -> SourceRoom:
    """A scene graph as the assembly takes it; its features are streamed from the hdf5
    files into the room's rows when the assembly fills them (the seconds spent add to
    clock["features"])."""
    def features(out: dict) -> None:
        t = time.perf_counter()
        try:
            stream_scene(g.folder, g.keys, det, layout, out["global_feat"],
                         out["appearance"], out["det_box"], out["det_conf"])
        finally:
            clock["features"] += time.perf_counter() - t
    return SourceRoom(scene_id=g.number, room_type=g.room_type, split=g.split,
                      next_state=g.next_state, pose=g.pose, visible=g.visible,
                      present=g.present, features=features)


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

    t1, clock = time.perf_counter(), {"features": 0.0}
    out = assemble([_room(g, det, layout, clock) for g, det in zip(graphs, det_paths)],
                   info=FORMAT_INFO + (("preset", "offline"),
                                       ("source", str(Path(offline_dir).resolve())),
                                       ("detection_file", det_paths[0].name)),
                   widths=(layout.appearance_dim, layout.global_dim), progress=progress)
    t_feat = clock["features"]
    t_expert = time.perf_counter() - t1 - t_feat    # the rest of assemble: expert tables
    per_scene = []
    for n, g in enumerate(graphs):
        rows = out.state_slice(n)
        rep = dict(g.report, detection_file=det_paths[n].name)
        if g.authors_action is not None:
            rep["optimal_action"] = compare_optimal(g.authors_action,
                                                    out.next_state[rows] - rows.start,
                                                    out.dist[rows], out.expert_action[rows],
                                                    g.keys)
        per_scene.append(rep)
    if splits is not None:  # custom names first: validate's messages use scene_names
        out = out.replace(info=out.info + (("splits", str(Path(splits).resolve())),) + (
            (("room_names", tuple(custom.values())), ("room_name_ids", tuple(custom)))
            if custom else ()))
    out.validate(str(offline_dir))
    opt = [r["optimal_action"] for r in per_scene if "optimal_action" in r]
    report = {
        "scenes": per_scene, "num_scenes": out.num_scenes, "states": out.num_states,
        "max_states": out.max_states, "global_dim": layout.global_dim,
        "appearance_dim": layout.appearance_dim, "detection_rows": int(layout.det_shape[0]),
        "seconds": {"json": round(t_json, 3), "features": round(t_feat, 3),
                    "expert": round(t_expert, 3)},
        "optimal_action": {k: sum(o[k] for o in opt) for k in
                           ("compared", "exact", "on_shortest_path", "mismatches",
                            "no_path_here")} if opt else None,
    }
    return out, report


def import_to(offline_dir: str | os.PathLike, out: str | os.PathLike,
              features: str | None = None, **kwargs) -> tuple[SceneSet, dict]:
    """import_offline, then scenes.save to `out` (loads with scenes.load(out)).
    features: 'float16' (default) or 'int8' (sceneset/quantize.py: per-channel scales).

    `out` must be absent, empty or a SceneSet (checked before importing); anything else
    is refused and left untouched."""
    if features is not None and features not in FEATURE_DTYPES:
        raise ValueError(f"features {features!r}: expected one of {list(FEATURE_DTYPES)}")
    check_output_dir(out, is_scene_set, "a SceneSet")
    scenes, report = import_offline(offline_dir, **kwargs)
    scenes = with_features(scenes, features)
    save(scenes, out, validate=False)  # import_offline validated it
    return scenes, report


def format_report(report: dict) -> str:
    """A few human lines about an import."""
    s = report["seconds"]
    lines = [(f"imported {report['num_scenes']} scene(s), {report['states']} states "
              f"(largest room {report['max_states']}), global 7x7x{report['global_dim']}, "
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
