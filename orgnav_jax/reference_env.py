"""A plain-Python navigation environment over dicts keyed by state strings.

It works the way the authors' offline controller does: the agent's pose is a string
"x|z|rotation|horizon"; MoveAhead computes the successor pose and fails if that pose is
not a known state; success is Done while the target is in the visible set of the state.
It shares no code with `orgnav_jax.env` (only the data), so tests use it as an oracle,
and `benchmarks/env_throughput.py` uses it as the "before".
"""

from __future__ import annotations

import math

import numpy as np

from orgnav_jax.constants import ACTIONS, CATEGORIES, GRID_SIZE, ROOM_TYPES, ROTATION_STEP
from orgnav_jax.scenes.sceneset.keys import parse_state_key, state_key

TRAIN_CAP, EVAL_CAP, EVAL_CAP_LIVING_ROOM = 30, 100, 200


class ReferenceScene:
    """One scene as dicts keyed by state string: the set of visible category names and
    the detections (box (C, 4), confidence (C,), float32 numpy)."""

    def __init__(self, name: str, room_type: str, keys: list[str], visible: dict[str, set],
                 detections: dict[str, tuple[np.ndarray, np.ndarray]]):
        self.name, self.room_type = name, room_type
        self.states = set(keys)
        self.visible = visible
        self.detections = detections

    @classmethod
    def from_sceneset(cls, scenes, n: int) -> ReferenceScene:
        rows = scenes.state_slice(n)         # the scene's states on the flat axis
        pose = np.asarray(scenes.pose[rows])
        vis = np.asarray(scenes.visible[rows])
        keys = [state_key(p) for p in pose]
        visible = {k: {CATEGORIES[c] for c in np.flatnonzero(v)} for k, v in zip(keys, vis)}
        box = np.asarray(scenes.det_box[rows]).astype(np.float32)
        conf = np.asarray(scenes.det_conf[rows]).astype(np.float32)
        detections = {k: (b, c) for k, b, c in zip(keys, box, conf)}
        return cls(scenes.scene_names[n], ROOM_TYPES[int(np.asarray(scenes.room_type)[n])],
                   keys, visible, detections)

    def successor(self, key: str, action: str) -> str:
        """The state after `action` (the same state if the action fails)."""
        x, z, rot, hor = parse_state_key(key)
        if action == "MoveAhead":
            rad = math.radians(rot)
            dx, dz = round(math.sin(rad), 6), round(math.cos(rad), 6)
            x += GRID_SIZE * (dx > 0) - GRID_SIZE * (dx < 0)
            z += GRID_SIZE * (dz > 0) - GRID_SIZE * (dz < 0)
        elif action == "RotateLeft":
            rot = (rot - ROTATION_STEP) % 360
        elif action == "RotateRight":
            rot = (rot + ROTATION_STEP) % 360
        elif action == "LookUp":
            hor = 0 if hor == 30 else -1
        elif action == "LookDown":
            hor = 30 if hor == 0 else -1
        new = state_key((x, z, rot, hor))
        return new if new in self.states else key


class ReferenceEnv:
    """Episodes on ReferenceScenes: reset(scene, state key, target name), then step(a).

    step returns (observation dict, reward, done, success); the observation holds the
    state key and the same arrays as orgnav_jax.env.Observation. path_len counts
    non-Done actions.
    """

    def __init__(self, scenes: dict[str, ReferenceScene], success_reward: float = 5.0,
                 step_penalty: float = -0.01, evaluation: bool = False):
        self.scenes = scenes
        self.success_reward, self.step_penalty = success_reward, step_penalty
        self.evaluation = evaluation

    @classmethod
    def from_sceneset(cls, scenes, **kw) -> ReferenceEnv:
        refs = [ReferenceScene.from_sceneset(scenes, n) for n in range(scenes.num_scenes)]
        return cls({r.name: r for r in refs}, **kw)

    def reset(self, scene: str, state: str, target: str) -> str:
        self.scene, self.state, self.target = self.scenes[scene], state, target
        self.steps = self.path_len = 0
        self.visited = {state}
        self.failed = self.revisited = False
        self.prev_action = -1
        if self.evaluation:
            self.cap = EVAL_CAP_LIVING_ROOM if self.scene.room_type == "living_room" else EVAL_CAP
        else:
            self.cap = TRAIN_CAP
        return self.observe()

    def observe(self) -> dict:
        box, conf = self.scene.detections[self.state]
        target = np.zeros(len(CATEGORIES), np.float32)
        target[CATEGORIES.index(self.target)] = 1.0
        prev = np.zeros(len(ACTIONS), np.float32)
        if self.prev_action >= 0:
            prev[self.prev_action] = 1.0
        return {"state": self.state, "det_box": box, "det_conf": conf, "target": target,
                "prev_action": prev, "deadlock": self.failed or self.revisited}

    def step(self, action: int) -> tuple[dict, float, bool, bool]:
        if not 0 <= action < len(ACTIONS):
            raise ValueError(f"action {action} outside 0..{len(ACTIONS) - 1} ({ACTIONS})")
        name = ACTIONS[action]
        self.prev_action = action
        self.steps += 1
        if name == "Done":
            success = self.target in self.scene.visible[self.state]
            self.failed = False
            done = True
        else:
            new = self.scene.successor(self.state, name)
            self.failed = new == self.state
            self.revisited = new in self.visited
            self.visited.add(new)
            self.state = new
            self.path_len += 1
            success = False
            done = self.steps >= self.cap
        reward = self.success_reward if success else self.step_penalty
        return self.observe(), reward, done, success
