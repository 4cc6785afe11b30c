"""Scene presets: how many rooms, and the decoded feature widths (G, d)."""

from __future__ import annotations

import dataclasses

from orgnav_jax.constants import FLOORPLAN_OFFSET, ROOM_TYPES, SPLITS


@dataclasses.dataclass(frozen=True)
class ScenePreset:
    """rooms_per_type: (train, val, test) rooms per room type (at most 20, 5, 5);
    global_dim: G, channels of the 7x7 global map; appearance_dim: d."""
    name: str
    rooms_per_type: tuple[int, int, int] = (20, 5, 5)
    global_dim: int = 32
    appearance_dim: int = 32

    def __post_init__(self):
        limits = (20, 5, 5)
        for split, n, hi in zip(SPLITS, self.rooms_per_type, limits):
            if not 0 <= n <= hi:
                raise ValueError(f"preset {self.name!r}: {n} {split} rooms per type, "
                                 f"expected 0..{hi} (AI2-THOR has 20/5/5)")
        for field in ("global_dim", "appearance_dim"):
            if getattr(self, field) < 1:
                raise ValueError(f"preset {self.name!r}: {field} must be >= 1")

    def floorplans(self) -> list[tuple[int, str, str]]:
        """(floorplan number, room type, split) for every room, in AI2-THOR order:
        train 1..20, val odd 21..29, test even 22..30 (+200/+300/+400 per type)."""
        n_train, n_val, n_test = self.rooms_per_type
        out = []
        for room_type in ROOM_TYPES:
            base = FLOORPLAN_OFFSET[room_type]
            out += [(base + k, room_type, "train") for k in range(1, n_train + 1)]
            out += [(base + 21 + 2 * k, room_type, "val") for k in range(n_val)]
            out += [(base + 22 + 2 * k, room_type, "test") for k in range(n_test)]
        return out


PRESETS: dict[str, ScenePreset] = {
    # The whole pipeline learns on 2 CPU cores in minutes.
    "small": ScenePreset("small", (20, 5, 5), global_dim=32, appearance_dim=32),
    # The paper's widths: ResNet-18 512x7x7 map, 512-d appearance features.
    "paper": ScenePreset("paper", (20, 5, 5), global_dim=512, appearance_dim=512),
    # For tests and quick demos: 2 train, 1 val, 1 test room per type.
    "tiny": ScenePreset("tiny", (2, 1, 1), global_dim=16, appearance_dim=16),
}


def get_preset(name: str | ScenePreset, **overrides) -> ScenePreset:
    """A preset by name, with fields replaced by `overrides`; clear errors otherwise."""
    if isinstance(name, ScenePreset):
        preset = name
    elif name in PRESETS:
        preset = PRESETS[name]
    else:
        raise ValueError(f"unknown scene preset {name!r}: expected one of {sorted(PRESETS)}")
    fields = {f.name for f in dataclasses.fields(ScenePreset)}
    bad = sorted(set(overrides) - fields)
    if bad:
        raise ValueError(f"unknown scene preset field(s) {bad}: expected some of {sorted(fields)}")
    return dataclasses.replace(preset, **overrides)
