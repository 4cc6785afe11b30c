"""Physical facts of the synthetic world: furniture kinds, object sizes, detector ranges,
and the co-occurrence rules the generator follows.

All numbers are in metres. Kept apart from the generator so that tests and docs can
read the rules without running anything.
"""

from __future__ import annotations

import dataclasses

from orgnav_jax.constants import CATEGORIES


@dataclasses.dataclass(frozen=True)
class FurnitureKind:
    name: str
    height: float       # top surface height (blocks sight below it)
    is_surface: bool    # objects may stand on it


FURNITURE: tuple[FurnitureKind, ...] = (
    FurnitureKind("counter", 0.90, True),
    FurnitureKind("stove", 0.90, True),
    FurnitureKind("sink_counter", 0.90, True),
    FurnitureKind("table", 0.75, True),
    FurnitureKind("sofa", 0.80, True),
    FurnitureKind("tv_stand", 0.55, True),
    FurnitureKind("coffee_table", 0.45, True),
    FurnitureKind("side_table", 0.60, True),
    FurnitureKind("shelf", 1.80, True),
    FurnitureKind("bed", 0.60, True),
    FurnitureKind("nightstand", 0.55, True),
    FurnitureKind("desk", 0.75, True),
    FurnitureKind("toilet", 0.45, False),
    FurnitureKind("bathtub", 0.55, False),
    FurnitureKind("vanity", 0.85, True),
    FurnitureKind("dresser", 0.95, True),
    FurnitureKind("island", 0.90, True),
    FurnitureKind("plant", 1.10, False),
    FurnitureKind("armchair", 0.80, True),
    FurnitureKind("stool", 0.60, True),
)
FURNITURE_INDEX = {f.name: i for i, f in enumerate(FURNITURE)}


@dataclasses.dataclass(frozen=True)
class ObjectKind:
    size: float          # footprint side (m)
    height: float        # vertical extent (m)
    detect_range: float  # distance at which the detector finds it half of the time (m)
    blocks: bool = False  # a floor object that blocks movement and sight of its cell


OBJECTS: dict[str, ObjectKind] = {
    "AlarmClock": ObjectKind(0.15, 0.10, 1.75),
    "Book": ObjectKind(0.20, 0.05, 2.0),
    "Bowl": ObjectKind(0.20, 0.08, 2.0),
    "CellPhone": ObjectKind(0.10, 0.02, 1.5),
    "Chair": ObjectKind(0.45, 0.90, 4.5, blocks=True),
    "CoffeeMachine": ObjectKind(0.25, 0.35, 2.75),
    "DeskLamp": ObjectKind(0.25, 0.45, 2.75),
    "FloorLamp": ObjectKind(0.35, 1.60, 4.5, blocks=True),
    "Fridge": ObjectKind(0.75, 1.80, 6.0, blocks=True),
    "GarbageCan": ObjectKind(0.30, 0.40, 3.0, blocks=True),
    "Kettle": ObjectKind(0.20, 0.25, 2.25),
    "Laptop": ObjectKind(0.35, 0.25, 2.5),
    "LightSwitch": ObjectKind(0.10, 0.12, 1.75),
    "Microwave": ObjectKind(0.50, 0.30, 3.5),
    "Pan": ObjectKind(0.30, 0.08, 2.25),
    "Plate": ObjectKind(0.25, 0.03, 2.0),
    "Pot": ObjectKind(0.30, 0.20, 2.5),
    "RemoteControl": ObjectKind(0.15, 0.03, 1.5),
    "Sink": ObjectKind(0.50, 0.20, 3.5),
    "StoveBurner": ObjectKind(0.22, 0.05, 3.0),
    "Television": ObjectKind(1.00, 0.60, 5.5),
    "Toaster": ObjectKind(0.25, 0.20, 2.25),
}
assert tuple(sorted(OBJECTS)) == tuple(sorted(CATEGORIES))

# "Small" targets: a detector only sees them up close (range <= 2.5 m).
SMALL_CATEGORIES: tuple[str, ...] = tuple(
    c for c in CATEGORIES if OBJECTS[c].detect_range <= 2.5
)

# Co-occurrence rules: a small object is placed near one of its anchors with
# probability ANCHOR_PROBABILITY (elsewhere on any surface otherwise). Tests check the
# resulting statistic; ORG is meant to learn it.
ANCHORS: dict[str, tuple[str, ...]] = {
    "Toaster": ("StoveBurner", "Sink"),
    "CoffeeMachine": ("StoveBurner", "Sink"),
    "Kettle": ("StoveBurner", "Sink"),
    "Pan": ("StoveBurner",),
    "Pot": ("StoveBurner",),
    "Bowl": ("Sink",),
    "Plate": ("Sink",),
    "RemoteControl": ("Television",),
    "Laptop": ("DeskLamp",),
    "CellPhone": ("DeskLamp", "Laptop"),
    "AlarmClock": ("DeskLamp",),
}
ANCHOR_PROBABILITY = 0.85
