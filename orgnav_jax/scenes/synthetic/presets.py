"""Scene presets: how many rooms, and the decoded feature widths (G, d)."""

from __future__ import annotations

import dataclasses
import numbers

import numpy as np

from orgnav_jax.constants import FLOORPLAN_OFFSET, ROOM_TYPES, SPLITS
from orgnav_jax.scenes.synthetic.catalog import ANCHOR_PROBABILITY
from orgnav_jax.scenes.synthetic.layout import ROOM_SIZE_PROFILES
from orgnav_jax.scenes.synthetic.perception import Perception


# The widest feature channel count a preset may ask for: 8x the paper's 512 (ResNet-18).
# A generated set holds (G, 49 x G)-ish projections and every model layer grows with the
# width; --global-dim 1e9 asked for 89 GB before this bound.
MAX_FEATURE_DIM = 4096
# The (min, max) optimal path length of evaluation episodes when a preset bounds none:
# any valid target at least one move away (ScenePreset.episode_distance).
DEFAULT_EPISODE_DISTANCE = (1, None)
EPISODE_DISTANCE_KEY = "episode_distance."     # + room type: its key in a set's info


@dataclasses.dataclass(frozen=True)
class ScenePreset:
    """rooms_per_type: (train, val, test) rooms per room type (at most 20, 5, 5);
    global_dim: G, channels of the 7x7 global map; appearance_dim: d;
    room_sizes: the generator's room-size profile (layout.ROOM_SIZE_PROFILES): "default"
      or "thor" (AI2-THOR's sizes: kitchens ~1,500 states, living rooms up to ~6,000);
    raw: store the decoded features themselves (bases None, like an import) instead of
      16-bit codes and projections; such sets are written to disk room by room
      (scenes.build_to), never built in memory;
    num_rooms: only this many of the rooms, taken in turn from each room type and,
      within a type, from each split (see floorplans); None = all of them;
    anchor_probability: how often an object with anchors is placed by one (the
      co-occurrence knob; catalog.ANCHOR_PROBABILITY by default);
    perception: the global view's and the detector's knobs (perception.py; the
      defaults are the clean perception of `small`);
    episode_distance: {room type: (min, max)} bounds on the optimal path length (moves)
      of the seeded evaluation episodes (episodes.sample_episodes; max None: no bound);
      room types not named keep (1, None), as does every type by default (None). Stored
      as ((room type, (min, max)), ...) for the named types, in ROOM_TYPES order."""
    name: str
    rooms_per_type: tuple[int, int, int] = (20, 5, 5)
    global_dim: int = 32
    appearance_dim: int = 32
    room_sizes: str = "default"
    raw: bool = False
    num_rooms: int | None = None
    anchor_probability: float = ANCHOR_PROBABILITY
    perception: Perception = Perception()
    episode_distance: tuple | None = None

    def __post_init__(self):
        if not isinstance(self.perception, Perception):
            raise ValueError(f"preset {self.name!r}: perception must be a Perception, got "
                             f"{type(self.perception).__name__}")
        # numbers of any kind (numpy's too) are kept as Python ints and floats, so that a
        # set's info is JSON and the cache's comparison sees plain numbers
        if isinstance(self.anchor_probability, bool) or \
                not isinstance(self.anchor_probability, numbers.Real) or \
                not 0.0 <= self.anchor_probability <= 1.0:
            raise ValueError(f"preset {self.name!r}: anchor_probability "
                             f"{self.anchor_probability!r}, expected 0 <= p <= 1")
        object.__setattr__(self, "anchor_probability", float(self.anchor_probability))
        limits = (20, 5, 5)
        if not isinstance(self.rooms_per_type, (tuple, list)) or \
                len(self.rooms_per_type) != 3 or not all(map(_integer, self.rooms_per_type)):
            raise ValueError(f"preset {self.name!r}: rooms_per_type must be (train, val, "
                             f"test) integers, got {self.rooms_per_type!r}")
        object.__setattr__(self, "rooms_per_type", tuple(int(n) for n in self.rooms_per_type))
        for field in ("global_dim", "appearance_dim", "num_rooms"):
            value = getattr(self, field)
            if value is None and field == "num_rooms":
                continue
            if not _integer(value):
                raise ValueError(f"preset {self.name!r}: {field} {value!r}, expected an "
                                 "integer")
            object.__setattr__(self, field, int(value))
        for split, n, hi in zip(SPLITS, self.rooms_per_type, limits):
            if not 0 <= n <= hi:
                raise ValueError(f"preset {self.name!r}: {n} {split} rooms per type, "
                                 f"expected 0..{hi} (AI2-THOR has 20/5/5)")
        for field in ("global_dim", "appearance_dim"):
            if not 1 <= getattr(self, field) <= MAX_FEATURE_DIM:
                raise ValueError(f"preset {self.name!r}: {field} {getattr(self, field)}, "
                                 f"expected 1..{MAX_FEATURE_DIM} (the paper's features are "
                                 "512 wide)")
        if self.room_sizes not in ROOM_SIZE_PROFILES:
            raise ValueError(f"preset {self.name!r}: room_sizes {self.room_sizes!r}, "
                             f"expected one of {sorted(ROOM_SIZE_PROFILES)}")
        object.__setattr__(self, "episode_distance",
                           _episode_distance(self.name, self.episode_distance))
        total = len(ROOM_TYPES) * sum(self.rooms_per_type)
        if self.num_rooms is not None and not 1 <= self.num_rooms <= total:
            raise ValueError(f"preset {self.name!r}: num_rooms {self.num_rooms}, expected "
                             f"1..{total} (rooms_per_type {tuple(self.rooms_per_type)} x "
                             f"{len(ROOM_TYPES)} room types)")

    def floorplans(self) -> list[tuple[int, str, str]]:
        """(floorplan number, room type, split) for every room, in AI2-THOR order:
        train 1..20, val odd 21..29, test even 22..30 (+200/+300/+400 per type).

        With num_rooms, the first num_rooms rooms of the round robin "kitchen, living
        room, bedroom, bathroom, kitchen, ..." where each type offers its rooms with the
        splits in turn (train, val, test, train, ...), kept in the order above: any
        count gets every room type and split the preset has, as evenly as possible."""
        n_train, n_val, n_test = self.rooms_per_type
        per_type = []
        for room_type in ROOM_TYPES:
            base = FLOORPLAN_OFFSET[room_type]
            per_type.append([[(base + k, room_type, "train") for k in range(1, n_train + 1)],
                             [(base + 21 + 2 * k, room_type, "val") for k in range(n_val)],
                             [(base + 22 + 2 * k, room_type, "test") for k in range(n_test)]])
        out = [room for splits in per_type for rooms in splits for room in rooms]
        if self.num_rooms is None:
            return out
        offered = [_round_robin(splits) for splits in per_type]
        chosen = set(_round_robin(offered)[:self.num_rooms])
        return [room for room in out if room in chosen]


def _integer(value) -> bool:
    """An integer of any kind (numpy's too), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def _episode_distance(name: str, value) -> tuple | None:
    """ScenePreset.episode_distance ({room type: (min, max)} or its stored form) ->
    ((room type, (min, max)), ...) for the types not at DEFAULT_EPISODE_DISTANCE, None
    when none is; one-line ValueError naming the field otherwise."""
    if value is None:
        return None
    field = f"preset {name!r}: episode_distance"
    try:
        bounds = dict(value)
    except (TypeError, ValueError):
        raise ValueError(f"{field} {value!r}, expected {{room type: (min, max)}}") from None
    out = []
    for room in ROOM_TYPES:
        if room not in bounds:
            continue
        pair = bounds.pop(room)
        if not isinstance(pair, (tuple, list)) or len(pair) != 2:
            raise ValueError(f"{field}[{room!r}] {pair!r}, expected (min, max)")
        lo, hi = pair
        if not _integer(lo) or lo < 0 or hi is not None and (not _integer(hi) or hi < lo):
            raise ValueError(f"{field}[{room!r}] {tuple(pair)!r}, expected integers 0 <= "
                             "min <= max (moves, 0: the target in view at the start; max "
                             "None: no bound)")
        pair = (int(lo), None if hi is None else int(hi))
        if pair != DEFAULT_EPISODE_DISTANCE:
            out.append((room, pair))
    if bounds:
        raise ValueError(f"{field}: unknown room type(s) {sorted(map(str, bounds))}, "
                         f"expected some of {list(ROOM_TYPES)}")
    return tuple(out) or None


def episode_distance_info(preset: ScenePreset) -> tuple:
    """The info pairs recording a preset's episode_distance: (("episode_distance.ROOM",
    (min, max)), ...) for the bounded room types; () by default (info unchanged)."""
    return tuple((EPISODE_DISTANCE_KEY + room, pair)
                 for room, pair in preset.episode_distance or ())


def parse_episode_distance(items: list[str]) -> dict:
    """["living_room=6", "kitchen=1:18", ...] -> {room type: (min, max or None)}
    (--episode-distance); ScenePreset checks the ranges, a one-line ValueError names a
    malformed item."""
    out = {}
    for item in items:
        room, _, bounds = item.partition("=")
        lo, _, hi = bounds.partition(":")
        try:
            if room not in ROOM_TYPES or room in out:
                raise ValueError(room)
            out[room] = (int(lo), int(hi) if hi else None)
        except ValueError:
            raise ValueError(f"episode_distance {item!r}: expected ROOM=MIN[:MAX] with ROOM "
                             f"one of {list(ROOM_TYPES)}, each room once") from None
    return out


def episode_bounds(info: tuple) -> dict[str, tuple[int, int | None]]:
    """A set's info -> {room type: (min, max)} for every room type: what
    episode_distance_info recorded, DEFAULT_EPISODE_DISTANCE where nothing is (the other
    presets, imported sets)."""
    info = dict(info)
    return {room: tuple(info.get(EPISODE_DISTANCE_KEY + room, DEFAULT_EPISODE_DISTANCE))
            for room in ROOM_TYPES}


def _round_robin(lists: list[list]) -> list:
    """[[a1, a2], [b1], [c1, c2, c3]] -> [a1, b1, c1, a2, c2, c3]."""
    out = []
    for k in range(max((len(x) for x in lists), default=0)):
        out += [x[k] for x in lists if k < len(x)]
    return out


# AI2-THOR-like perception (docs/calibrated.md): the global view without object labels,
# with per-state noise and a per-room style; a detector with shorter range, lower recall,
# no tiny boxes, more and confident false positives, confusions, jittered boxes and
# noisier appearance. Chosen on val (experiments/results/calibration, setting g3d1) so
# that WE and the Baseline score there what they score in AI2-THOR; frozen.
CALIBRATED_PERCEPTION = Perception(
    global_labels="furniture", global_noise=0.35, room_style=0.35,
    detect_range_scale=0.7, peak_recall=0.8, min_box_area=64.0, false_positive_rate=0.05,
    fp_confidence_max=0.7, confidence_noise=0.15, confusion=0.15, box_jitter=5.0,
    appearance_noise=1.0)

# The same, calibrated again for agents trained to convergence (22 M env steps: docs/
# results.md, "The converged table"): chosen on val at that budget (experiments/results/
# calibration/at_22000000, setting g5d6v): a noisier global view and a detector halfway
# between `calibrated`'s and a poorer one; frozen.
CALIBRATED_22M_PERCEPTION = Perception(
    global_labels="furniture", global_noise=0.65, room_style=0.65,
    detect_range_scale=0.6, peak_recall=0.75, min_box_area=104.0, false_positive_rate=0.075,
    fp_confidence_max=0.8, confidence_noise=0.175, confusion=0.225, box_jitter=7.5,
    appearance_noise=1.25)
# Evaluation episodes that may start with the target in view, as the authors' do.
IN_VIEW_EPISODES = {room: (0, None) for room in ROOM_TYPES}

SCENE_PRESETS: dict[str, ScenePreset] = {
    # The whole pipeline learns on 2 CPU cores in minutes.
    "small": ScenePreset("small", (20, 5, 5), global_dim=32, appearance_dim=32),
    # `small`'s rooms, splits and episodes with the calibrated perception above.
    "calibrated": ScenePreset("calibrated", (20, 5, 5), global_dim=32, appearance_dim=32,
                              perception=CALIBRATED_PERCEPTION),
    # `small`'s rooms and splits with the perception above and episodes that may start
    # in view: the benchmark of the converged table.
    "calibrated_22m": ScenePreset("calibrated_22m", (20, 5, 5), global_dim=32,
                                  appearance_dim=32, perception=CALIBRATED_22M_PERCEPTION,
                                  episode_distance=IN_VIEW_EPISODES),
    # The paper's widths: ResNet-18 512x7x7 map, 512-d appearance features.
    "paper": ScenePreset("paper", (20, 5, 5), global_dim=512, appearance_dim=512),
    # For tests and quick demos: 2 train, 1 val, 1 test room per type.
    "tiny": ScenePreset("tiny", (2, 1, 1), global_dim=16, appearance_dim=16),
    # Real size, like an import of the authors' data: AI2-THOR's room sizes, paper widths,
    # decoded float16 features (bases None). Default: the 40 val + test rooms (88 k
    # states, 6.4 GB of features); choose fewer with num_rooms or rooms_per_type. Built to disk only
    # (python -m orgnav_jax.scenes build --preset large --out DIR; scenes.build_to).
    "large": ScenePreset("large", (0, 5, 5), global_dim=512, appearance_dim=512,
                         room_sizes="thor", raw=True),
}


def get_preset(name: str | ScenePreset, **overrides) -> ScenePreset:
    """A preset by name, with fields replaced by `overrides`; clear errors otherwise."""
    if isinstance(name, ScenePreset):
        preset = name
    elif name in SCENE_PRESETS:
        preset = SCENE_PRESETS[name]
    else:
        raise ValueError(f"unknown scene preset {name!r}: expected one of {sorted(SCENE_PRESETS)}")
    fields = {f.name for f in dataclasses.fields(ScenePreset)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"unknown scene preset field(s) {bad}: expected some of {sorted(fields)}")
    return dataclasses.replace(preset, **overrides)
