"""Procedural room layouts: floor plan, walls, furniture and object placement (numpy).

`generate_room(seed, floorplan)` is a pure function of its arguments: the same
(seed, floorplan) gives the same room, whatever other rooms are built.

Grid convention: cell (i, j) is the grid point x = j * 0.25 m, z = i * 0.25 m. The outer
ring of the array is wall; L-shaped rooms wall off a corner block.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from orgnav_jax.constants import (
    CATEGORY_INDEX, FLOORPLAN_OFFSET, GRID_SIZE, ROOM_TYPES,
)
from orgnav_jax.scenes.synthetic.catalog import (
    ANCHOR_PROBABILITY, ANCHORS, FURNITURE, FURNITURE_INDEX, OBJECTS,
)

# Interior size ranges in cells (rows, cols), and reachable-cell bounds per room type.
ROOM_SIZE = {
    "kitchen": ((12, 17), (13, 19)),
    "living_room": ((17, 23), (18, 25)),
    "bedroom": ((14, 19), (15, 21)),
    "bathroom": ((8, 11), (9, 13)),
}
REACHABLE_RANGE = {
    "kitchen": (60, 260), "living_room": (150, 380),
    "bedroom": (90, 320), "bathroom": (40, 120),
}
# AI2-THOR's room sizes (preset 'large', room_sizes="thor"): 16 states per reachable cell,
# so kitchens ~1,500 states (900-2,200), living rooms ~4,000 (1,600-6,100), bedrooms
# ~2,100 (1,200-3,700), bathrooms ~1,000 (640-1,500); iTHOR's rooms span 576-6,160.
THOR_ROOM_SIZE = {
    "kitchen": ((10, 14), (10, 16)),
    "living_room": ((10, 22), (11, 24)),
    "bedroom": ((11, 16), (12, 18)),
    "bathroom": ((8, 11), (9, 13)),
}
THOR_REACHABLE_RANGE = {
    "kitchen": (56, 140), "living_room": (100, 382),
    "bedroom": (75, 230), "bathroom": (40, 95),
}
ROOM_SIZE_PROFILES = {  # name -> (interior size ranges, reachable-cell bounds)
    "default": (ROOM_SIZE, REACHABLE_RANGE),
    "thor": (THOR_ROOM_SIZE, THOR_REACHABLE_RANGE),
}
WALL_OBJECT_HEIGHT = (1.15, 1.40)  # LightSwitch centre height range (m)


@dataclasses.dataclass
class Room:
    """One generated room. Grid arrays are (H, W); objects are K instances."""
    floorplan: int
    room_type: str
    wall: np.ndarray          # (H, W) bool, full-height walls
    furniture: np.ndarray     # (H, W) int, furniture kind index or -1
    block_height: np.ndarray  # (H, W) float, height that blocks sight (inf on walls)
    reachable: np.ndarray     # (H, W) bool, cells the agent can stand on (connected)
    obj_category: np.ndarray  # (K,) int, category index
    obj_center: np.ndarray    # (K, 3) float, x, y (centre height), z in metres
    obj_size: np.ndarray      # (K,) float, footprint side (m)
    obj_height: np.ndarray    # (K,) float, vertical extent (m)
    door: tuple[int, int]     # wall cell of the door

    @property
    def name(self) -> str:
        return f"FloorPlan{self.floorplan}"


def room_type_of(floorplan: int) -> str:
    """Room type from AI2-THOR numbering: 1-30 kitchen, 201-230 living room, ..."""
    for name, offset in FLOORPLAN_OFFSET.items():
        if offset + 1 <= floorplan <= offset + 30:
            return name
    raise ValueError(
        f"floorplan {floorplan} is outside AI2-THOR numbering (1-30, 201-230, 301-330, 401-430)"
    )


class _Builder:
    """Mutable workspace while one room is laid out."""

    def __init__(self, rng: np.random.Generator, room_type: str,
                 room_size: dict = ROOM_SIZE, anchor_probability: float = ANCHOR_PROBABILITY):
        self.rng = rng
        self.room_type = room_type
        self.anchor_probability = anchor_probability
        (r0, r1), (c0, c1) = room_size[room_type]
        rows, cols = int(rng.integers(r0, r1 + 1)), int(rng.integers(c0, c1 + 1))
        self.wall = np.ones((rows + 2, cols + 2), bool)
        self.wall[1:-1, 1:-1] = False
        if rng.random() < 0.4:  # L-shape: wall off a corner block
            cut_r = int(rng.integers(rows // 4, rows // 2 + 1))
            cut_c = int(rng.integers(cols // 4, cols // 2 + 1))
            rs = slice(1, 1 + cut_r) if rng.random() < 0.5 else slice(rows + 1 - cut_r, rows + 1)
            cs = slice(1, 1 + cut_c) if rng.random() < 0.5 else slice(cols + 1 - cut_c, cols + 1)
            self.wall[rs, cs] = True
        self.furniture = np.full(self.wall.shape, -1, np.int32)
        self.block_height = np.where(self.wall, np.inf, 0.0)
        self.reserved = np.zeros(self.wall.shape, bool)  # kept free (door clearance)
        self.objects: list[tuple[int, float, float, float, float, float]] = []
        self.door = self._make_door()

    # ----------------------------------------------------------------- geometry helpers
    def _neighbours_wall(self) -> np.ndarray:
        """(H, W) bool: interior cells 4-adjacent to a wall cell."""
        w = np.pad(self.wall, 1, constant_values=True)
        adj = w[:-2, 1:-1] | w[2:, 1:-1] | w[1:-1, :-2] | w[1:-1, 2:]
        return adj & ~self.wall

    def free(self) -> np.ndarray:
        return ~self.wall & (self.furniture < 0) & (self.block_height == 0)

    def _make_door(self) -> tuple[int, int]:
        h, w = self.wall.shape
        cands = []
        for i in range(1, h - 1):
            for j in range(1, w - 1):
                if self.wall[i, j]:
                    continue
                for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    wi, wj = i + di, j + dj
                    # a straight wall run: both wall neighbours along it are walls
                    if self.wall[wi, wj] and (
                        (di != 0 and self.wall[wi, wj - 1] and self.wall[wi, wj + 1]
                         and not self.wall[i, j - 1] and not self.wall[i, j + 1])
                        or (dj != 0 and 0 < wi < h - 1 and self.wall[wi - 1, wj]
                            and self.wall[wi + 1, wj] and not self.wall[i - 1, j]
                            and not self.wall[i + 1, j])
                    ):
                        cands.append((wi, wj, i, j))
        wi, wj, i, j = cands[int(self.rng.integers(len(cands)))]
        self.reserved[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2] = True
        self.reserved &= ~self.wall
        return wi, wj

    def _rects(self, h: int, w: int) -> list[tuple[int, int, int, int]]:
        """All (i0, j0, h, w) rectangles of free, unreserved cells (both orientations)."""
        ok = self.free() & ~self.reserved
        out = []
        for hh, ww in {(h, w), (w, h)}:
            H, W = ok.shape
            for i in range(H - hh + 1):
                for j in range(W - ww + 1):
                    if ok[i:i + hh, j:j + ww].all():
                        out.append((i, j, hh, ww))
        return out

    def place_furniture(self, kind: str, dims: tuple[int, int], *, against_wall: bool,
                        near: np.ndarray | None = None, far: np.ndarray | None = None,
                        clearance: bool = False) -> np.ndarray | None:
        """Place a (rows, cols) rectangle of furniture; returns its (H, W) mask or None.

        against_wall: one long side touches walls; clearance: a free ring around it
        (free-standing pieces keep a passage); near/far: prefer cells near/far a mask.
        """
        wall_adj = self._neighbours_wall()
        cands, scores = [], []
        for i, j, hh, ww in self._rects(*dims):
            if against_wall:
                sides = ([wall_adj[i, j:j + ww], wall_adj[i + hh - 1, j:j + ww]] if ww >= hh
                         else [wall_adj[i:i + hh, j], wall_adj[i:i + hh, j + ww - 1]])
                if not any(s.all() for s in sides):
                    continue
            if clearance:
                ring = self.free()[max(i - 1, 0):i + hh + 1, max(j - 1, 0):j + ww + 1]
                if not ring.all():
                    continue
            score = 0.0
            ci, cj = i + (hh - 1) / 2, j + (ww - 1) / 2
            if near is not None and near.any():
                score -= _min_dist(near, ci, cj)
            if far is not None and far.any():
                score += 0.5 * _min_dist(far, ci, cj)
            cands.append((i, j, hh, ww))
            scores.append(score)
        if not cands:
            return None
        k = _softmax_choice(self.rng, np.asarray(scores), temperature=1.0)
        i, j, hh, ww = cands[k]
        mask = np.zeros(self.wall.shape, bool)
        mask[i:i + hh, j:j + ww] = True
        self.furniture[mask] = FURNITURE_INDEX[kind]
        self.block_height[mask] = FURNITURE[FURNITURE_INDEX[kind]].height
        return mask

    # ------------------------------------------------------------------- objects
    def add_object(self, category: str, x: float, y_bottom: float, z: float) -> None:
        kind = OBJECTS[category]
        self.objects.append((CATEGORY_INDEX[category], x, y_bottom + kind.height / 2, z,
                             kind.size, kind.height))

    def object_mask(self, category: str) -> np.ndarray:
        """(H, W) bool: cells holding an instance of the category."""
        mask = np.zeros(self.wall.shape, bool)
        for cat, x, _, z, _, _ in self.objects:
            if cat == CATEGORY_INDEX[category]:
                mask[int(round(z / GRID_SIZE)), int(round(x / GRID_SIZE))] = True
        return mask

    def place_on_surface(self, category: str, kinds: tuple[str, ...],
                         cells: np.ndarray | None = None) -> bool:
        """Put one instance on a furniture top of the given kinds (or on given cells).

        Objects with anchors go near an anchor instance with probability
        self.anchor_probability (default ANCHOR_PROBABILITY). The draws are the same for
        every probability (one coin, one choice over the same cells), so the knob moves
        only where anchored objects land.
        """
        if cells is None:
            kind_ids = [FURNITURE_INDEX[k] for k in kinds]
            cells = np.isin(self.furniture, kind_ids)
        cand = np.argwhere(cells)
        if len(cand) == 0:
            return False
        weights = np.ones(len(cand))
        anchor_mask = np.zeros(self.wall.shape, bool)
        for a in ANCHORS.get(category, ()):
            anchor_mask |= self.object_mask(a)
        if anchor_mask.any() and self.rng.random() < self.anchor_probability:
            d = np.array([_min_dist(anchor_mask, i, j) for i, j in cand])
            weights = np.exp(-(d - d.min()) / 1.5) * (d > 0)
            if weights.sum() == 0:
                weights = np.ones(len(cand))
        i, j = cand[self.rng.choice(len(cand), p=weights / weights.sum())]
        x = j * GRID_SIZE + self.rng.uniform(-0.08, 0.08)
        z = i * GRID_SIZE + self.rng.uniform(-0.08, 0.08)
        y = FURNITURE[self.furniture[i, j]].height
        self.add_object(category, x, y, z)
        return True

    def place_on_floor(self, category: str, next_to: np.ndarray) -> bool:
        """Put a floor object on a free cell 8-adjacent to `next_to`; blocking ones
        occupy a k x k cell block (k = size / grid)."""
        k = max(1, int(round(OBJECTS[category].size / GRID_SIZE)))
        grown = _dilate(next_to)
        ok = self.free() & ~self.reserved
        cands = []
        H, W = ok.shape
        for i in range(H - k + 1):
            for j in range(W - k + 1):
                if ok[i:i + k, j:j + k].all() and grown[i:i + k, j:j + k].any():
                    cands.append((i, j))
        if not cands:
            return False
        i, j = cands[int(self.rng.integers(len(cands)))]
        kind = OBJECTS[category]
        if kind.blocks:
            self.block_height[i:i + k, j:j + k] = kind.height
        ci, cj = i + (k - 1) / 2, j + (k - 1) / 2
        self.add_object(category, cj * GRID_SIZE, 0.0, ci * GRID_SIZE)
        return True

    def place_on_wall_by_door(self, category: str) -> None:
        """A wall object (LightSwitch) on the wall next to the door, facing the room."""
        wi, wj = self.door
        cands = []
        for di in range(-3, 4):
            for dj in range(-3, 4):
                i, j = wi + di, wj + dj
                if (0 <= i < self.wall.shape[0] and 0 <= j < self.wall.shape[1]
                        and self.wall[i, j] and (i, j) != (wi, wj)):
                    for ni, nj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
                        if (0 <= ni < self.wall.shape[0] and 0 <= nj < self.wall.shape[1]
                                and not self.wall[ni, nj]):
                            cands.append((i, j, ni, nj))
        i, j, ni, nj = cands[int(self.rng.integers(len(cands)))]
        x = (j + 0.6 * (nj - j)) * GRID_SIZE
        z = (i + 0.6 * (ni - i)) * GRID_SIZE
        y = self.rng.uniform(*WALL_OBJECT_HEIGHT) - OBJECTS[category].height / 2
        self.add_object(category, x, y, z)

    def finish(self, floorplan: int) -> Room:
        reachable = _largest_component(self.free())
        objs = np.asarray(self.objects, np.float64).reshape(-1, 6)
        return Room(
            floorplan=floorplan, room_type=self.room_type, wall=self.wall,
            furniture=self.furniture, block_height=self.block_height.astype(np.float32),
            reachable=reachable, obj_category=objs[:, 0].astype(np.int32),
            obj_center=objs[:, 1:4].astype(np.float32), obj_size=objs[:, 4].astype(np.float32),
            obj_height=objs[:, 5].astype(np.float32), door=self.door,
        )


# ---------------------------------------------------------------------- room recipes
def _kitchen(b: _Builder) -> None:
    rng = b.rng
    counter = b.place_furniture("counter", (2, int(rng.integers(8, 13))), against_wall=True)
    if counter is None:
        raise _Retry
    # stove and sink segments inside the counter run
    cells = np.argwhere(counter)
    along_j = np.ptp(cells[:, 1]) > np.ptp(cells[:, 0])
    axis = cells[:, 1] if along_j else cells[:, 0]
    lo, hi = axis.min(), axis.max()
    s0 = int(rng.integers(lo, hi - 1))
    k0 = int(rng.integers(lo, hi - 1))
    while abs(k0 - s0) < 3:
        k0 = int(rng.integers(lo, hi - 1))
    stove = counter & np.isin(np.indices(counter.shape)[1 if along_j else 0], [s0, s0 + 1])
    sink = counter & np.isin(np.indices(counter.shape)[1 if along_j else 0], [k0, k0 + 1])
    b.furniture[stove] = FURNITURE_INDEX["stove"]
    b.furniture[sink] = FURNITURE_INDEX["sink_counter"]
    for i, j in np.argwhere(stove):
        b.add_object("StoveBurner", j * GRID_SIZE, FURNITURE[FURNITURE_INDEX["stove"]].height,
                     i * GRID_SIZE)
    si, sj = np.argwhere(sink).mean(0)
    b.add_object("Sink", sj * GRID_SIZE, 0.70, si * GRID_SIZE)
    if rng.random() < 0.6:  # a second counter run
        b.place_furniture("counter", (2, int(rng.integers(4, 8))), against_wall=True,
                          near=counter)
    if not b.place_on_floor("Fridge", counter):
        b.place_on_floor("Fridge", b.wall)
    island = b.place_furniture("island" if rng.random() < 0.5 else "table",
                               (int(rng.integers(2, 4)), int(rng.integers(3, 6))),
                               against_wall=False, clearance=True)
    counters = np.isin(b.furniture, [FURNITURE_INDEX[k] for k in ("counter", "stove",
                                                                     "sink_counter")])
    tops = ("counter", "island", "table", "sink_counter")
    b.place_on_surface("Microwave", ("counter", "island"))
    for cat in ("Toaster", "CoffeeMachine", "Kettle"):
        if rng.random() < 0.9:
            b.place_on_surface(cat, ("counter", "island"))
    for cat in ("Pan", "Pot"):
        if rng.random() < 0.9:
            b.place_on_surface(cat, ("stove", "counter"))
    for cat in ("Bowl", "Plate"):
        for _ in range(int(rng.integers(1, 3))):
            b.place_on_surface(cat, tops)
    b.place_on_surface("CellPhone", tops)
    if rng.random() < 0.3:
        b.place_on_surface("Book", tops)
    seat_anchor = island if island is not None else counters
    for _ in range(int(rng.integers(1, 4))):
        b.place_on_floor("Chair", seat_anchor)
    b.place_on_floor("GarbageCan", counters)
    b.place_on_wall_by_door("LightSwitch")


def _living_room(b: _Builder) -> None:
    rng = b.rng
    sofa = b.place_furniture("sofa", (3, int(rng.integers(6, 10))), against_wall=True)
    if sofa is None:
        raise _Retry
    tv = b.place_furniture("tv_stand", (2, int(rng.integers(4, 7))), against_wall=True,
                           far=sofa)
    if tv is None:
        raise _Retry
    ti, tj = np.argwhere(tv).mean(0)
    b.add_object("Television", tj * GRID_SIZE, FURNITURE[FURNITURE_INDEX["tv_stand"]].height,
                 ti * GRID_SIZE)
    table = b.place_furniture("coffee_table", (2, int(rng.integers(3, 6))),
                              against_wall=False, near=sofa | tv, clearance=True)
    b.place_furniture("side_table", (2, 2), against_wall=True, near=sofa)
    for _ in range(int(rng.integers(1, 3))):
        b.place_furniture("shelf", (1, int(rng.integers(3, 7))), against_wall=True)
    desk = None
    if rng.random() < 0.7:
        desk = b.place_furniture("desk", (2, int(rng.integers(4, 7))), against_wall=True)
    b.place_on_floor("FloorLamp", sofa)
    b.place_on_surface("DeskLamp", ("side_table", "desk"))
    b.place_on_surface("RemoteControl", ("coffee_table", "sofa", "tv_stand"))
    b.place_on_surface("Laptop", ("desk", "coffee_table", "sofa"))
    b.place_on_surface("CellPhone", ("coffee_table", "sofa", "desk", "side_table"))
    for _ in range(int(rng.integers(1, 4))):
        b.place_on_surface("Book", ("shelf", "shelf", "coffee_table"))
    for _ in range(int(rng.integers(1, 3))):
        b.place_on_floor("Chair", desk if desk is not None else (table if table is not None
                                                                  else sofa))
    b.place_on_floor("GarbageCan", desk if desk is not None else sofa)
    b.place_on_wall_by_door("LightSwitch")


def _bedroom(b: _Builder) -> None:
    rng = b.rng
    bed = b.place_furniture("bed", (int(rng.integers(6, 9)), int(rng.integers(5, 8))),
                            against_wall=True)
    if bed is None:
        raise _Retry
    stands = [b.place_furniture("nightstand", (2, 2), against_wall=True, near=bed)
              for _ in range(int(rng.integers(1, 3)))]
    desk = b.place_furniture("desk", (2, int(rng.integers(4, 7))), against_wall=True,
                             far=bed)
    b.place_furniture("shelf" if rng.random() < 0.5 else "dresser",
                      (int(rng.integers(1, 3)), int(rng.integers(3, 6))), against_wall=True)
    if any(s is not None for s in stands) and rng.random() < 0.7:
        b.place_on_surface("DeskLamp", ("nightstand",))
    else:
        b.place_on_surface("DeskLamp", ("desk", "nightstand"))
    b.place_on_surface("AlarmClock", ("nightstand", "dresser", "desk", "shelf"))
    b.place_on_surface("Laptop", ("desk", "bed"))
    b.place_on_surface("CellPhone", ("bed", "nightstand", "desk"))
    for _ in range(int(rng.integers(1, 4))):
        b.place_on_surface("Book", ("shelf", "dresser", "desk", "nightstand", "bed"))
    anchor = desk if desk is not None else bed
    b.place_on_floor("Chair", anchor)
    b.place_on_floor("GarbageCan", anchor)
    b.place_on_wall_by_door("LightSwitch")


def _bathroom(b: _Builder) -> None:
    rng = b.rng
    vanity = b.place_furniture("vanity", (2, int(rng.integers(3, 5))), against_wall=True)
    if vanity is None:
        raise _Retry
    vi, vj = np.argwhere(vanity).mean(0)
    b.add_object("Sink", vj * GRID_SIZE, 0.65, vi * GRID_SIZE)
    toilet = b.place_furniture("toilet", (2, 2), against_wall=True, near=vanity)
    b.place_furniture("bathtub", (3, int(rng.integers(6, 8))), against_wall=True)
    b.place_on_floor("GarbageCan", toilet if toilet is not None and rng.random() < 0.5
                     else vanity)
    b.place_on_wall_by_door("LightSwitch")


_RECIPES = {"kitchen": _kitchen, "living_room": _living_room, "bedroom": _bedroom,
            "bathroom": _bathroom}


class _Retry(Exception):
    """A recipe could not fit its furniture: draw a new floor plan."""


def _partition_wall(b: _Builder) -> None:
    """A wall stub from one side 35-65 % into the room: a corner to get stuck behind."""
    rng = b.rng
    H, W = b.wall.shape
    vertical = rng.random() < 0.5
    n_across, n_along = (W, H) if vertical else (H, W)
    pos = int(rng.integers(n_across // 3, 2 * n_across // 3 + 1))
    length = int(round((n_along - 2) * rng.uniform(0.35, 0.65)))
    cells = np.arange(1, 1 + length) if rng.random() < 0.5 else np.arange(n_along - 1 - length, n_along - 1)
    stub = np.zeros_like(b.wall)
    if vertical:
        stub[cells, pos] = True
    else:
        stub[pos, cells] = True
    if (stub & b.reserved).any():
        return
    b.wall |= stub
    b.block_height[stub] = np.inf


def _clutter(b: _Builder) -> None:
    """Free-standing obstacles (plants, armchairs, stools) that narrow the passages."""
    area = int((~b.wall).sum())
    for _ in range(int(b.rng.integers(1, 2 + area // 80))):
        kind = ("plant", "armchair", "stool")[int(b.rng.integers(3))]
        dims = {"plant": (1, 1), "armchair": (2, 2), "stool": (1, 1)}[kind]
        b.place_furniture(kind, dims, against_wall=b.rng.random() < 0.5)


def generate_room(seed: int, floorplan: int, max_tries: int = 50,
                  room_sizes: str = "default",
                  anchor_probability: float = ANCHOR_PROBABILITY) -> Room:
    """Lay out one room deterministically from (seed, floorplan, room_sizes,
    anchor_probability).

    room_sizes: a ROOM_SIZE_PROFILES name: "default" (the tiny/small/paper presets) or
    "thor" (AI2-THOR's room sizes, preset 'large'). anchor_probability: how often an
    object with anchors (catalog.ANCHORS) is put next to one (0: anywhere on its
    surfaces, 1: always by an anchor when the room has one); the same seed gives the same
    room apart from where those objects go. Returns a Room whose reachable-cell count
    lies in the profile's reachable range for its type.
    """
    if not 0.0 <= anchor_probability <= 1.0:
        raise ValueError(f"anchor_probability {anchor_probability!r}: expected 0 <= p <= 1")
    room_type = room_type_of(floorplan)
    assert room_type in ROOM_TYPES
    if room_sizes not in ROOM_SIZE_PROFILES:
        raise ValueError(f"unknown room_sizes {room_sizes!r}: expected one of "
                         f"{sorted(ROOM_SIZE_PROFILES)}")
    room_size, reachable_range = ROOM_SIZE_PROFILES[room_sizes]
    lo, hi = reachable_range[room_type]
    for attempt in range(max_tries):
        rng = np.random.default_rng([seed, floorplan, attempt])
        b = _Builder(rng, room_type, room_size, anchor_probability)
        if room_type != "bathroom" and rng.random() < 0.5:
            _partition_wall(b)
        try:
            _RECIPES[room_type](b)
            _clutter(b)
        except _Retry:
            continue
        room = b.finish(floorplan)
        if lo <= room.reachable.sum() <= hi:
            return room
    raise RuntimeError(f"could not lay out {room_type} FloorPlan{floorplan} in {max_tries} tries")


def render_ascii(room: Room) -> str:
    """Top view for docs and debugging: # wall, = furniture, o blocking object,
    . reachable, * object, D door, blank = unreachable free floor."""
    g = np.full(room.wall.shape, " ")
    g[room.furniture >= 0] = "="
    g[(room.block_height > 0) & (room.furniture < 0)] = "o"
    g[room.wall] = "#"
    g[room.reachable] = "."
    for x, _, z in room.obj_center:
        g[int(round(z / GRID_SIZE)), int(round(x / GRID_SIZE))] = "*"
    g[room.door] = "D"
    return "\n".join("".join(row) for row in g)


# ----------------------------------------------------------------------- small utils
def _min_dist(mask: np.ndarray, i: float, j: float) -> float:
    pts = np.argwhere(mask)
    return float(np.sqrt(((pts - np.array([i, j])) ** 2).sum(1)).min())


def _softmax_choice(rng: np.random.Generator, scores: np.ndarray, temperature: float) -> int:
    p = np.exp((scores - scores.max()) / temperature)
    return int(rng.choice(len(p), p=p / p.sum()))


def _dilate(mask: np.ndarray) -> np.ndarray:
    m = np.pad(mask, 1)
    out = np.zeros_like(mask)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            out |= m[1 + di:1 + di + mask.shape[0], 1 + dj:1 + dj + mask.shape[1]]
    return out


def _largest_component(free: np.ndarray) -> np.ndarray:
    """Largest 8-connected component of free cells (diagonal moves are allowed)."""
    label = np.full(free.shape, -1, np.int32)
    sizes = []
    for start in map(tuple, np.argwhere(free)):
        if label[start] >= 0:
            continue
        k = len(sizes)
        stack, n = [start], 0
        label[start] = k
        while stack:
            i, j = stack.pop()
            n += 1
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    ni, nj = i + di, j + dj
                    if (0 <= ni < free.shape[0] and 0 <= nj < free.shape[1]
                            and free[ni, nj] and label[ni, nj] < 0):
                        label[ni, nj] = k
                        stack.append((ni, nj))
        sizes.append(n)
    if not sizes:
        return np.zeros_like(free)
    return label == int(np.argmax(sizes))
