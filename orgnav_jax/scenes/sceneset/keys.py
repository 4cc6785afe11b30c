"""State keys in the authors' form: "x|z|rotation|horizon", e.g. "-1.25|2.75|315|30".

x and z carry two decimals; rotation and horizon are whole degrees.
"""

from __future__ import annotations

import numpy as np


def state_key(pose) -> str:
    """(4,) pose (x, z, rotation, horizon) -> "x|z|rot|hor"."""
    x, z, rot, hor = (float(v) for v in pose)
    return f"{x:.2f}|{z:.2f}|{int(round(rot)) % 360}|{int(round(hor))}"


def parse_state_key(key: str) -> tuple[float, float, int, int]:
    """"x|z|rot|hor" -> (x, z, rotation, horizon); ValueError on a malformed key."""
    parts = str(key).split("|")
    try:
        if len(parts) != 4:
            raise ValueError
        x, z = float(parts[0]), float(parts[1])
        rot, hor = int(round(float(parts[2]))), int(round(float(parts[3])))
    except ValueError:
        raise ValueError(f"malformed state key {key!r}: expected 'x|z|rotation|horizon', "
                         "e.g. '-1.25|2.75|315|30'") from None
    return x, z, rot % 360, hor


def scene_state_keys(pose: np.ndarray, count: int) -> list[str]:
    """(S, 4) poses of one scene, its number of valid states -> their keys."""
    return [state_key(p) for p in np.asarray(pose)[:count]]


def key_index(pose: np.ndarray, count: int) -> dict[str, int]:
    """{state key: state index} for one scene's valid states."""
    return {k: i for i, k in enumerate(scene_state_keys(pose, count))}
