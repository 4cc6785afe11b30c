"""Facts of the task: categories, actions, room types, targets (paper + authors' episodes).

Everything here is a plain tuple or dict so it can be imported anywhere (numpy, JAX,
scripts) without side effects.
"""

from __future__ import annotations

# The 22 categories, in the paper's (and the authors' detection files') order.
CATEGORIES: tuple[str, ...] = (
    "AlarmClock", "Book", "Bowl", "CellPhone", "Chair", "CoffeeMachine", "DeskLamp",
    "FloorLamp", "Fridge", "GarbageCan", "Kettle", "Laptop", "LightSwitch", "Microwave",
    "Pan", "Plate", "Pot", "RemoteControl", "Sink", "StoveBurner", "Television", "Toaster",
)
NUM_CATEGORIES = len(CATEGORIES)  # C = 22
CATEGORY_INDEX: dict[str, int] = {name: i for i, name in enumerate(CATEGORIES)}

# Actions, indices 0..5.
ACTIONS: tuple[str, ...] = (
    "MoveAhead", "RotateLeft", "RotateRight", "LookUp", "LookDown", "Done",
)
NUM_ACTIONS = len(ACTIONS)  # A = 6
MOVE_AHEAD, ROTATE_LEFT, ROTATE_RIGHT, LOOK_UP, LOOK_DOWN, DONE = range(NUM_ACTIONS)

# Room types in AI2-THOR FloorPlan numbering order (1-30, 201-230, 301-330, 401-430).
ROOM_TYPES: tuple[str, ...] = ("kitchen", "living_room", "bedroom", "bathroom")
ROOM_TYPE_INDEX: dict[str, int] = {name: i for i, name in enumerate(ROOM_TYPES)}
FLOORPLAN_OFFSET: dict[str, int] = {
    "kitchen": 0, "living_room": 200, "bedroom": 300, "bathroom": 400,
}

SPLITS: tuple[str, ...] = ("train", "val", "test")
SPLIT_INDEX: dict[str, int] = {name: i for i, name in enumerate(SPLITS)}

# Target categories per room type in the authors' val/test episodes.
TARGETS: dict[str, tuple[str, ...]] = {
    "kitchen": (
        "Bowl", "CellPhone", "Chair", "CoffeeMachine", "Fridge", "GarbageCan", "Kettle",
        "LightSwitch", "Microwave", "Pan", "Plate", "Pot", "Sink", "StoveBurner", "Toaster",
    ),
    "living_room": (
        "Book", "CellPhone", "Chair", "DeskLamp", "FloorLamp", "GarbageCan", "Laptop",
        "LightSwitch", "RemoteControl", "Television",
    ),
    "bedroom": (
        "AlarmClock", "Book", "CellPhone", "Chair", "DeskLamp", "GarbageCan", "Laptop",
        "LightSwitch",
    ),
    "bathroom": ("GarbageCan", "LightSwitch", "Sink"),
}

# Grid and camera geometry shared by the generator and the environment.
GRID_SIZE = 0.25           # metres per grid step
ROTATION_STEP = 45         # degrees per RotateLeft/RotateRight
NUM_HEADINGS = 8           # 0, 45, ..., 315
# (di, dj) grid step of MoveAhead for headings 0, 45, ..., 315 degrees: 0 -> +z (di=+1),
# 90 -> +x (dj=+1); diagonal headings step on both axes.
HEADING_STEP: tuple[tuple[int, int], ...] = (
    (1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1),
)
HORIZONS: tuple[int, ...] = (0, 30)  # degrees below the horizontal (30 = looking down)
VISIBILITY_DISTANCE = 1.5  # metres: a target counts as visible within this distance
FIELD_OF_VIEW = 90.0       # degrees, horizontal and vertical (square image)
IMAGE_SIZE = 300           # pixels, detections are boxes in a 300x300 image
CAMERA_HEIGHT = 1.5        # metres above the floor
FEATURE_GRID = 7           # the global feature map is 7x7


def category_index(name: str) -> int:
    """Index of a category name; a clear error for a name outside the 22."""
    try:
        return CATEGORY_INDEX[name]
    except KeyError:
        raise ValueError(
            f"unknown category {name!r}: expected one of the 22 categories {list(CATEGORIES)}"
        ) from None


def room_type_index(name: str) -> int:
    """Index of a room type name; a clear error otherwise."""
    try:
        return ROOM_TYPE_INDEX[name]
    except KeyError:
        raise ValueError(
            f"unknown room type {name!r}: expected one of {list(ROOM_TYPES)}"
        ) from None


def split_index(name: str) -> int:
    """Index of a split name ('train', 'val', 'test'); a clear error otherwise."""
    try:
        return SPLIT_INDEX[name]
    except KeyError:
        raise ValueError(f"unknown split {name!r}: expected one of {list(SPLITS)}") from None

# Evaluation episodes per room type in the test protocol (the paper's 250 per room type).
EPISODES_PER_ROOM_TYPE = 250

# The scene preset every entry point uses when none is named: `small`'s rooms and episodes
# with AI2-THOR-like perception (docs/calibrated.md); `small` stays available by name.
DEFAULT_SCENE_PRESET = "calibrated"
