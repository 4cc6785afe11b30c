"""Read the JSON part of one offline scene folder: states, transitions, visibility and
(optionally) the authors' optimal actions. Features (hdf5) are in features_io.py."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from orgnav_jax.constants import ACTIONS, NUM_ACTIONS, NUM_CATEGORIES
from orgnav_jax.errors import is_number, shown
from orgnav_jax.scenes.offline import files
from orgnav_jax.scenes.offline.graph import grid_states, state_order, transitions
from orgnav_jax.scenes.offline.validate import (
    OfflineFormatError, check_same_keys, check_type, examples, floorplan_number, load_json,
    object_type, parse_keys, room_type_and_split,
)


@dataclasses.dataclass
class SceneGraph:
    """One scene without features; S states in our order (row, col, heading, horizon)."""
    folder: Path
    number: int                 # AI2-THOR FloorPlan number
    room_type: int
    split: int
    keys: list[str]             # (S,) state keys
    pose: np.ndarray            # (S, 4) float32 x, z (authors' metres), rotation, horizon
    next_state: np.ndarray      # (S, A) int32
    visible: np.ndarray         # (S, C) bool
    present: np.ndarray         # (C,) bool: an object of the type is in the visibility map
    authors_action: np.ndarray | None  # (S, C) int8 from optimal_action.json, -1 = none
    report: dict


def _graph_keys_and_edges(path: Path):
    doc = load_json(path, "networkx node_link_data of the state graph")
    what = f"{path}"
    if not isinstance(doc, dict) or not isinstance(doc.get("nodes"), list):
        raise OfflineFormatError(f"{what}: expected an object with a 'nodes' list "
                                 "(networkx node_link_data)")
    links = doc.get("links", doc.get("edges"))
    if not isinstance(links, list):
        raise OfflineFormatError(f"{what}: expected a 'links' (or 'edges') list of "
                                 "{'source': key, 'target': key}")
    keys = []
    for i, node in enumerate(doc["nodes"]):
        if not isinstance(node, dict) or not isinstance(node.get("id"), str):
            raise OfflineFormatError(f"{what}: node {i} is {shown(node)}, expected {{'id': key}}")
        keys.append(node["id"])
    if not keys:
        raise OfflineFormatError(f"{what}: the graph has no nodes")
    if len(set(keys)) != len(keys):
        dup = [k for k in set(keys) if keys.count(k) > 1]
        raise OfflineFormatError(f"{what}: duplicate node ids {examples(dup)}")
    pairs = []
    for i, link in enumerate(links):
        if not isinstance(link, dict) or not all(isinstance(link.get(k), str)
                                                 for k in ("source", "target")):
            raise OfflineFormatError(f"{what}: link {i} is {shown(link)}, expected "
                                     "{'source': key, 'target': key}")
        pairs.append((link["source"], link["target"]))
    directed = doc.get("directed", True)
    if not isinstance(directed, bool):
        raise OfflineFormatError(f"{what}: field 'directed' is {shown(directed)}, expected "
                                 "true or false")
    return keys, pairs, directed


def _check_grid(path: Path, keys: list[str], pose: np.ndarray) -> int:
    """Every state's (x, z) must be a point of grid.json; returns points without states."""
    grid = load_json(path, "list of reachable points {'x', 'y', 'z'}")
    if not isinstance(grid, list):
        raise OfflineFormatError(f"{path}: expected a list of points {{'x', 'y', 'z'}}")
    points = set()
    for i, p in enumerate(grid):
        if not isinstance(p, dict) or not all(is_number(p.get(k)) and p[k] == p[k]
                                              for k in ("x", "z")):
            raise OfflineFormatError(f"{path}: point {i} is {shown(p)}, expected "
                                     "{'x': float, 'y': float, 'z': float} (finite numbers)")
        points.add((round(float(p["x"]) * 100), round(float(p["z"]) * 100)))
    cells = {(round(x * 100), round(z * 100)) for x, z in pose[:, :2]}
    missing = cells - points
    if missing:
        bad = [k for k, (x, z) in zip(keys, pose[:, :2])
               if (round(x * 100), round(z * 100)) in missing]
        raise OfflineFormatError(f"{path}: {len(missing)} position(s) of graph.json states are "
                                 f"not reachable points here, e.g. states {examples(bad)}")
    return len(points - cells)


def _visibility(folder: Path, index: dict[str, int], unknown_types: str, report: dict):
    path = next((folder / n for n in files.VISIBLE_FILES if (folder / n).is_file()), None)
    if path is None:
        raise OfflineFormatError(f"{folder}: missing file {files.VISIBLE_FILES[0]} (objectId "
                                 "-> state keys where it is visible within 1.5 m)")
    doc = load_json(path, "objectId -> list of state keys")
    if not isinstance(doc, dict):
        raise OfflineFormatError(f"{path}: expected an object mapping objectId -> state keys")
    first = next(iter(doc), "")
    if first.split("|")[0].lstrip("-").replace(".", "", 1).isdigit():
        raise OfflineFormatError(f"{path}: keyed by state ({first!r}), i.e. raw per-state "
                                 "metadata; expected objectId -> list of state keys")
    visible = np.zeros((len(index), NUM_CATEGORIES), bool)
    present = np.zeros(NUM_CATEGORIES, bool)
    ignored: set[str] = set()
    for oid, states in doc.items():
        c = check_type(object_type(oid, str(path)), str(path), unknown_types, ignored)
        if c is None:
            continue
        if not isinstance(states, list):
            raise OfflineFormatError(f"{path}: objectId {oid!r} maps to {type(states).__name__},"
                                     " expected a list of state keys")
        present[c] = True
        unknown = [s for s in states if not isinstance(s, str) or s not in index]
        if unknown:
            raise OfflineFormatError(f"{path}: objectId {oid!r} lists {len(unknown)} state "
                                     f"key(s) not in graph.json: {examples(unknown)}")
        visible[[index[s] for s in states], c] = True
    report.update(visibility_file=path.name, ignored_types=sorted(ignored))
    return visible, present


def _authors_actions(path: Path, keys: list[str], index: dict[str, int], unknown_types: str,
                     report: dict) -> np.ndarray:
    doc = load_json(path, "state key -> {target type: action index}")
    if not isinstance(doc, dict):
        raise OfflineFormatError(f"{path}: expected an object state key -> {{type: action}}")
    check_same_keys(str(path), doc.keys(), f"{path.parent / files.GRAPH_FILE}", keys)
    out = np.full((len(keys), NUM_CATEGORIES), -1, np.int8)
    ignored: set[str] = set()
    for key, per_type in doc.items():
        if not isinstance(per_type, dict):
            raise OfflineFormatError(f"{path}: state {key!r} maps to {shown(per_type)}, expected "
                                     "{target type: action index}")
        for name, a in per_type.items():
            c = check_type(name, f"{path} (state {key!r})", unknown_types, ignored)
            if c is None:
                continue
            if isinstance(a, str) and a in ACTIONS:
                a = ACTIONS.index(a)
            if isinstance(a, bool) or not isinstance(a, int) or not 0 <= a < NUM_ACTIONS:
                raise OfflineFormatError(f"{path}: state {key!r} target {name!r} has action "
                                         f"{a!r}, expected an index 0..5 or a name in {ACTIONS}")
            out[index[key], c] = a
    report["optimal_ignored_types"] = sorted(ignored)
    return out


def read_scene(folder: Path, unknown_types: str = "ignore", unmatched_edges: str = "error",
               assignment: tuple[int, int, int] | None = None) -> SceneGraph:
    """Parse and cross-check graph.json, grid.json, the visibility map and (when present)
    optimal_action.json of one FloorPlanN folder. assignment: (scene_id, room type,
    split) from a splits file (splits.py), for any folder name; default: from N."""
    folder = Path(folder)
    if assignment is not None:
        number, room_type, split = assignment
    else:
        number = floorplan_number(folder.name, str(folder))
        room_type, split = room_type_and_split(number, str(folder))
    graph_path = folder / files.GRAPH_FILE
    raw_keys, pairs, directed = _graph_keys_and_edges(graph_path)
    raw_pose = parse_keys(raw_keys, str(graph_path))
    grid = grid_states(raw_pose, raw_keys, str(graph_path))
    order = state_order(grid)
    keys = [raw_keys[i] for i in order]
    pose, grid = raw_pose[order], grid[order]
    index = {k: i for i, k in enumerate(keys)}
    ends = [k for pair in pairs for k in pair if k not in index]
    if ends:
        raise OfflineFormatError(f"{graph_path}: {len(ends)} link end(s) are not graph nodes: "
                                 f"{examples(set(ends))}")
    src = np.array([index[s] for s, _ in pairs], np.int64)
    dst = np.array([index[t] for _, t in pairs], np.int64)
    nxt, ignored_edges = transitions(grid, src, dst, keys, str(graph_path), directed,
                                     unmatched_edges)
    report = {"scene": folder.name, "states": len(keys), "edges": len(pairs),
              "ignored_edges": ignored_edges,
              "grid_points_without_states": _check_grid(folder / files.GRID_FILE, keys, pose)}
    visible, present = _visibility(folder, index, unknown_types, report)
    opt_path = folder / files.OPTIMAL_FILE
    authors = (_authors_actions(opt_path, keys, index, unknown_types, report)
               if opt_path.is_file() else None)
    return SceneGraph(folder=folder, number=number, room_type=room_type, split=split,
                      keys=keys, pose=pose.astype(np.float32), next_state=nxt,
                      visible=visible, present=present, authors_action=authors, report=report)
