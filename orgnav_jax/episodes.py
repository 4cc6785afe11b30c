"""Fixed, seeded evaluation episodes: sample, save to JSON, load and check against scenes.

The EpisodeSet type and its records live in the data model (scenes/sceneset/episodes.py,
re-exported here). An EpisodeSet indexes one SceneSet (usually a split view): episode e starts in scene
`scene[e]` at state `start[e]` looking for category `target[e]`. `start` is the room's
LOCAL state index (0..state_count-1), independent of how the SceneSet lays its rooms out;
env.start_episode turns it into the global flat index (state_offset[scene] + start). On
disk, episodes are stored in the authors' form (scene name, goal_object_type, state key) plus
`optimal_len`, so a file names rooms and poses, never array indices:

    {"format": "orgnav_jax.episodes/1", "split": "test", "seed": 0, "scenes": {...},
     "episodes": [{"scene": "FloorPlan22", "goal_object_type": "Microwave",
                   "state": "1.25|2.00|90|30", "optimal_len": 9}, ...]}
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from orgnav_jax.constants import (  # noqa: F401  (EPISODES_PER_ROOM_TYPE re-exported)
    EPISODES_PER_ROOM_TYPE, ROOM_TYPES,
)
from orgnav_jax.errors import read_int, read_str
from orgnav_jax.safe_write import write_text_atomic
from orgnav_jax.scenes.sceneset.episodes import (  # noqa: F401  (the data type, re-exported)
    EpisodeSet, from_records, to_records,
)
from orgnav_jax.scenes.sceneset.fields import UNREACHABLE
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.synthetic.presets import DEFAULT_EPISODE_DISTANCE, episode_bounds

FORMAT = "orgnav_jax.episodes/1"


def sample_episodes(scenes: SceneSet, per_room_type: int = EPISODES_PER_ROOM_TYPE,
                    seed: int = 0, min_dist: int = 1, split: str = "") -> EpisodeSet:
    """Seeded episodes: for each room type present, `per_room_type` episodes, each a
    scene of that type (uniform), a start state (uniform over the scene's states) and a
    valid target (uniform over those whose distance from the start lies within the (min,
    max) its preset's episode_distance sets for the room type, episode_bounds of the set's
    info; where it sets none, at distance >= min_dist (0: the target may be in view at
    the start); a start with no such target is drawn again)."""
    if isinstance(per_room_type, bool) or not isinstance(per_room_type, (int, np.integer)) \
            or per_room_type < 1:
        raise ValueError(f"episodes per room type: {per_room_type!r}, expected an integer "
                         ">= 1")
    rng = np.random.default_rng(seed)
    room_type = np.asarray(scenes.room_type)
    counts = np.asarray(scenes.state_count)
    offsets = np.asarray(scenes.state_offset)
    targets = np.asarray(scenes.targets)
    dist = np.asarray(scenes.dist)                     # (T, C)
    bounds = episode_bounds(scenes.info)
    out = {k: [] for k in ("scene", "start", "target", "optimal_len", "room_type")}
    for t in range(len(ROOM_TYPES)):
        of_type = np.flatnonzero(room_type == t)
        if of_type.size == 0:
            continue
        lo, hi = bounds[ROOM_TYPES[t]]
        if (lo, hi) == DEFAULT_EPISODE_DISTANCE:     # the preset bounds none: min_dist
            lo = min_dist                           # (0: the target may be in view)
        hi = UNREACHABLE - 1 if hi is None else hi
        _check_sampleable(scenes, of_type, ROOM_TYPES[t], lo, hi, split)
        made = 0
        while made < per_room_type:
            n = int(rng.choice(of_type))
            s = int(rng.integers(counts[n]))
            d = dist[offsets[n] + s].astype(np.int64)
            ok = np.flatnonzero(targets[n] & (d >= lo) & (d <= hi))
            if ok.size == 0:
                continue
            c = int(rng.choice(ok))
            for k, v in zip(out, (n, s, c, int(d[c]), t)):
                out[k].append(v)
            made += 1
    arrays = {k: np.asarray(v, np.int32) for k, v in out.items()}
    return EpisodeSet(**arrays, split=split, seed=seed)


def _check_sampleable(scenes: SceneSet, of_type: np.ndarray, room: str, lo: int, hi: int,
                      split: str) -> None:
    """ValueError unless some scene in `of_type` has a start state with a valid target at
    a distance in lo..hi (else sampling that room type would never end)."""
    for n in of_type:
        d = np.asarray(scenes.dist[scenes.state_slice(n)])
        if ((d >= lo) & (d <= hi) & np.asarray(scenes.targets[n])[None]).any():
            return
    names = ", ".join(scenes.scene_names[n] for n in of_type[:5])
    within = f">= {lo}" if hi == UNREACHABLE - 1 else f"{lo}..{hi}"
    raise ValueError(f"no episode can be sampled for the {room} rooms"
                     f"{f' of split {split}' if split else ''} ({names}"
                     f"{', ...' if of_type.size > 5 else ''}): no valid target is reachable "
                     f"from any state at distance {within}")


def length_stats(episodes: EpisodeSet) -> dict[str, dict]:
    """Optimal path lengths (moves: the non-Done actions of a shortest path to a state
    where the target is visible, `optimal_len`) of an episode set, per room type present
    and over all: {"kitchen": {"episodes": n, "mean": float, "median": float}, ...,
    "all": {...}}."""
    length = np.asarray(episodes.optimal_len, np.float64)        # (E,)
    room_type = np.asarray(episodes.room_type)                    # (E,)
    groups = [(name, room_type == t) for t, name in enumerate(ROOM_TYPES)]
    groups.append(("all", np.ones(len(length), bool)))
    return {name: {"episodes": int(mask.sum()), "mean": float(length[mask].mean()),
                   "median": float(np.median(length[mask]))}
            for name, mask in groups if mask.any()}


def save_episodes(path: str | os.PathLike, episodes: EpisodeSet, scenes: SceneSet) -> None:
    """Write episodes as JSON (atomically: a temporary file, then a rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"format": FORMAT, "split": episodes.split, "seed": episodes.seed,
           "scenes": {k: v for k, v in scenes.info if isinstance(v, (int, str, float))},
           "episodes": to_records(episodes, scenes)}
    lines = ",\n".join(json.dumps(r) for r in doc.pop("episodes"))  # one episode a line
    text = json.dumps(doc)[:-1] + ', "episodes": [\n' + lines + "\n]}\n"
    write_text_atomic(path, text)


def is_episode_file(path: str | os.PathLike) -> bool:
    """Whether `path` is an episode file save_episodes wrote (a JSON object of FORMAT);
    False for anything unreadable, binary or other JSON."""
    try:
        with open(path, "rb") as f:
            head = f.read(200)
        if not head.lstrip().startswith(b"{") or FORMAT.encode() not in head:
            return False
        doc = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and doc.get("format") == FORMAT \
        and isinstance(doc.get("episodes"), list)


def load_episodes(path: str | os.PathLike, scenes: SceneSet) -> EpisodeSet:
    """Read an episode file written by save_episodes (or a bare list of authors'
    records) and map it onto `scenes`; clear errors if it does not fit them. The typed
    reader of episode files: an object {"format", "split": "" or a split name, "seed":
    int32 >= 0, "episodes": [records]} (or a bare list of records); each record's fields
    typed by from_records. One-line ValueErrors name the file, the episode and field."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"episode file {path} does not exist")
    if path.is_dir():
        raise IsADirectoryError(f"episode file {path} is a directory, expected a JSON file")
    data = path.read_bytes()
    expected = (f"expected a JSON episode file (format {FORMAT}, written by "
                "orgnav_jax.evaluate) or a JSON list of episodes")
    try:
        doc = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        kind = "a Python pickle" if data[:1] == b"\x80" else "binary data"
        raise ValueError(f"episode file {path} is {kind}, not JSON text; {expected} (the "
                         "authors' pickles load safely with "
                         "orgnav_jax.scenes.offline.episodes.load_offline_episodes)") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"episode file {path} is not valid JSON: {err}") from None
    except RecursionError:
        raise ValueError(f"episode file {path}: JSON nested too deeply to read; "
                         f"{expected}") from None
    if isinstance(doc, list):
        doc = {"episodes": doc}
    if not isinstance(doc, dict) or not isinstance(doc.get("episodes"), list):
        raise ValueError(f"episode file {path}: expected an object with an 'episodes' list "
                         f"(format {FORMAT}) or a list of episodes")
    if "format" in doc and doc["format"] != FORMAT:
        raise ValueError(f"episode file {path}: format {doc['format']!r}, expected {FORMAT!r}")
    source = f"episode file {path}"
    split = read_str(doc, "split", source, choices=("", "train", "val", "test"), default="")
    seed = read_int(doc, "seed", source, default=0)
    episodes, _ = from_records(doc["episodes"], scenes, source=source, split=split,
                               seed=seed)
    return episodes
