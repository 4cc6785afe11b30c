"""Summary statistics of a SceneSet, as a dict and as a printed table."""

from __future__ import annotations

import dataclasses

import numpy as np

from orgnav_jax.constants import CATEGORIES, ROOM_TYPES, SPLITS, TARGETS, category_index
from orgnav_jax.scenes.synthetic.catalog import ANCHOR_PROBABILITY
from orgnav_jax.scenes.synthetic.perception import Perception
from orgnav_jax.scenes.synthetic.presets import (
    DEFAULT_EPISODE_DISTANCE, SCENE_PRESETS, episode_bounds)
from orgnav_jax.scenes.sceneset.fields import PER_STATE_FIELDS, UNREACHABLE
from orgnav_jax.scenes.sceneset.sceneset import SceneSet


def summarize(scenes: SceneSet) -> dict:
    """Rooms per split and type, state counts, target reachability, feature sizes.

    reachable_share[room_type][target]: over rooms of that type holding the target, the
    share of start states from which some state seeing it can be reached.
    """
    n_states = np.asarray(scenes.state_count).astype(np.int64)
    offsets = np.asarray(scenes.state_offset)
    room_type, split = np.asarray(scenes.room_type), np.asarray(scenes.split)
    present = np.asarray(scenes.present)
    dist = np.asarray(scenes.dist)          # (T, C)
    rooms = {s: {t: int(((split == i) & (room_type == j)).sum())
                 for j, t in enumerate(ROOM_TYPES)} for i, s in enumerate(SPLITS)}
    share = {}
    for j, t in enumerate(ROOM_TYPES):
        share[t] = {}
        for name in TARGETS[t]:
            c = category_index(name)
            idx = np.flatnonzero((room_type == j) & present[:, c])
            if idx.size == 0:
                share[t][name] = None
                continue
            ok = sum(int((dist[offsets[n]:offsets[n] + n_states[n], c] < UNREACHABLE).sum())
                     for n in idx)
            share[t][name] = float(ok / n_states[idx].sum())
    per_state = sum(np.asarray(getattr(scenes, f)).nbytes
                    for f in PER_STATE_FIELDS) / max(scenes.num_states, 1)
    return {
        "preset": scenes.meta("preset"), "seed": scenes.meta("seed"),
        "anchor_probability": scenes.meta("anchor_probability", ANCHOR_PROBABILITY
                                          if scenes.meta("preset") in SCENE_PRESETS
                                          else None),
        "perception": perception_of(scenes),
        "episode_distance": {room: list(b) for room, b in episode_bounds(scenes.info).items()
                             if b != DEFAULT_EPISODE_DISTANCE},
        "num_scenes": scenes.num_scenes, "states_total": scenes.num_states,
        "rooms": rooms,
        "states": {"min": int(n_states.min()), "median": float(np.median(n_states)),
                   "max": int(n_states.max())},
        "states_by_type": {t: float(np.median(n_states[room_type == j]))
                           for j, t in enumerate(ROOM_TYPES) if (room_type == j).any()},
        "reachable_share": share,
        "features": {
            "global": f"7x7x{scenes.global_dim}",
            "appearance": f"{len(CATEGORIES)}x{scenes.appearance_dim}",
            "stored_global": f"7x7x{scenes.global_feat.shape[-1]} {scenes.global_feat.dtype}",
            "stored_appearance": f"{len(CATEGORIES)}x{scenes.appearance.shape[-1]} "
                                 f"{scenes.appearance.dtype}",
            "bytes_per_state": round(per_state, 1),
            "feature_bytes": int(scenes.appearance.nbytes + scenes.global_feat.nbytes),
        },
    }


def perception_of(scenes: SceneSet) -> dict | None:
    """Every perception knob of a generated set ({knob: value}: the defaults with the
    values its info records, perception.py), None for a set of another source (an
    import: its perception is whatever its detector and backbone were)."""
    if scenes.meta("preset") not in SCENE_PRESETS:
        return None
    knobs = dataclasses.asdict(Perception())
    for key, value in scenes.info:
        if key.startswith("perception.") and key[len("perception."):] in knobs:
            knobs[key[len("perception."):]] = value
    return knobs


def format_summary(s: dict) -> str:
    """The dict from `summarize` as a human table."""
    lines = [f"SceneSet preset={s['preset']} seed={s['seed']}: {s['num_scenes']} rooms, "
             f"{s['states_total']} states (flat, unpadded)"]
    if s.get("anchor_probability") is not None:
        lines.append(f"anchor probability {s['anchor_probability']:g} (objects placed by "
                     "their anchors; the generator's default is "
                     f"{ANCHOR_PROBABILITY:g})")
    if s.get("perception") is not None:
        changed = {k: v for k, v in s["perception"].items()
                   if v != getattr(Perception(), k)}
        lines.append("perception: " + (", ".join(f"{k} {v}" for k, v in changed.items())
                                       + " (other knobs at their defaults)" if changed else
                                       "every knob at its default (small's clean "
                                       "perception)"))
    if s.get("episode_distance"):
        lines.append("evaluation episodes' optimal path length (moves) bounded: " + ", ".join(
            f"{room} {lo}..{'' if hi is None else hi}"
            for room, (lo, hi) in s["episode_distance"].items()))
    lines.append(f"{'rooms':<8}" + "".join(f"{t:>13}" for t in ROOM_TYPES))
    for split, per in s["rooms"].items():
        lines.append(f"{split:<8}" + "".join(f"{per[t]:>13}" for t in ROOM_TYPES))
    st = s["states"]
    lines.append(f"states per room: min {st['min']}  median {st['median']:.0f}  max {st['max']}"
                 "  (median by type: " + ", ".join(f"{t} {v:.0f}" for t, v in
                                                     s["states_by_type"].items()) + ")")
    lines.append("share of start states from which the target is reachable:")
    for t, per in s["reachable_share"].items():
        cells = [f"{name} {v:.2f}" if v is not None else f"{name} -" for name, v in per.items()]
        lines.append(f"  {t:<12} " + ", ".join(cells))
    f = s["features"]
    lines.append(f"features: global {f['global']} (stored {f['stored_global']}), appearance "
                 f"{f['appearance']} (stored {f['stored_appearance']}), "
                 f"{f['bytes_per_state']:.0f} bytes/state, "
                 f"{f['feature_bytes'] / 2**20:.1f} MB of features")
    if "disk_mb" in s:
        lines.append(f"disk: {s['disk_mb']:.1f} MB")
    if "build_s" in s:
        lines.append(f"build time: {s['build_s']:.1f} s")
    return "\n".join(lines)
