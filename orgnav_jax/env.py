"""The navigation environment as pure functions (gymnax style), for vmap and jit.

    obs, state = reset(key, scenes, params)
    obs, state, reward, done, info = step(key, state, action, scenes, params)  # auto-reset
    obs, state, reward, done, info = step_env(state, action, scenes, params)  # no reset

`scenes` is a SceneSet (usually one split's view, moved to device); `params` is a static
EnvParams. All shapes below are per environment; vmap adds the batch axis in front.

Path lengths count the moving actions (MoveAhead, Rotate*, Look*), not the final Done:
an episode's L is its number of non-Done steps and L_opt = scenes.dist at the start, so
the expert has L = L_opt and SPL 1.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from orgnav_jax.constants import DONE, NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES
from orgnav_jax.scenes.sceneset import SceneSet

START_TRIES = 4  # start states drawn per reset; the first with a valid target is kept


@struct.dataclass
class EnvParams:
    """Static settings (hashable, so jit specializes on them)."""
    success_reward: float = struct.field(pytree_node=False, default=5.0)
    step_penalty: float = struct.field(pytree_node=False, default=-0.01)  # paper: -0.001
    max_steps: tuple[int, ...] = struct.field(pytree_node=False, default=(30, 30, 30, 30))
    min_start_dist: int = struct.field(pytree_node=False, default=1)

    @classmethod
    def evaluation(cls, **kw) -> "EnvParams":
        """The paper's evaluation caps: 100 steps, 200 in living rooms."""
        caps = tuple(200 if t == "living_room" else 100 for t in ROOM_TYPES)
        return cls(max_steps=caps, **kw)


@struct.dataclass
class EnvState:
    scene: jax.Array        # () int32 index into the SceneSet
    state: jax.Array        # () int32 state index in that scene
    target: jax.Array       # () int32 category index
    steps: jax.Array        # () int32 actions taken this episode (Done included)
    path_len: jax.Array     # () int32 non-Done actions taken
    prev_action: jax.Array  # () int32, -1 at episode start
    last_failed: jax.Array  # () bool: the last action left the agent where it was
    revisited: jax.Array    # () bool: the current state was visited before this episode
    trail: jax.Array        # (T+1,) int32 states visited this episode, -1 beyond; T = max cap
    optimal_len: jax.Array  # () int32 shortest path length at the start


@struct.dataclass
class Observation:
    scene: jax.Array        # () int32: with `state`, the index of the large features
    state: jax.Array        # () int32
    det_box: jax.Array      # (C, 4) float32 box in pixels (x1, y1, x2, y2), 0 if none
    det_conf: jax.Array     # (C,) float32 confidence, 0 = no detection
    target: jax.Array       # (C,) float32 one-hot target category
    prev_action: jax.Array  # (A,) float32 one-hot previous action, zeros at start
    deadlock: jax.Array     # () bool: revisited state or failed last action


def observe(state: EnvState, scenes: SceneSet) -> Observation:
    """The observation of an EnvState (gathers the small per-state arrays)."""
    return Observation(
        scene=state.scene, state=state.state,
        det_box=scenes.det_box[state.scene, state.state].astype(jnp.float32),
        det_conf=scenes.det_conf[state.scene, state.state].astype(jnp.float32),
        target=jax.nn.one_hot(state.target, NUM_CATEGORIES),
        prev_action=jax.nn.one_hot(state.prev_action, NUM_ACTIONS),
        deadlock=state.last_failed | state.revisited,
    )


def start_episode(scene: jax.Array, start: jax.Array, target: jax.Array,
                  scenes: SceneSet, params: EnvParams) -> EnvState:
    """The EnvState at the start of a given episode (scene, start state, target).

    The visited set is a trail of at most max(params.max_steps) + 1 states: far smaller
    than a bitset over S, and an any() over it is cheap.
    """
    trail = jnp.full(max(params.max_steps) + 1, -1, jnp.int32).at[0].set(start)
    return EnvState(
        scene=scene, state=start, target=target, steps=jnp.int32(0), path_len=jnp.int32(0),
        prev_action=jnp.int32(-1), last_failed=jnp.bool_(False), revisited=jnp.bool_(False),
        trail=trail,
        optimal_len=scenes.dist[scene, start, target].astype(jnp.int32),
    )


def sample_episode(key: jax.Array, scenes: SceneSet, params: EnvParams):
    """A random (scene, start, target): a scene uniformly, a start state uniformly among
    its states, a target uniformly among its valid targets whose distance from the start
    is at least params.min_start_dist. Returns three () int32."""
    k_scene, k_start, k_target = jax.random.split(key, 3)
    scene = jax.random.randint(k_scene, (), 0, scenes.num_scenes)
    starts = jax.random.randint(k_start, (START_TRIES,), 0, scenes.state_count[scene])
    d = scenes.dist[scene, starts].astype(jnp.int32)                       # (T, C)
    ok = scenes.targets[scene][None] & (d >= params.min_start_dist)        # (T, C)
    pick = jnp.argmax(ok.any(1))
    logits = jnp.where(ok[pick], 0.0, -jnp.inf)
    target = jax.random.categorical(k_target, logits).astype(jnp.int32)
    return scene.astype(jnp.int32), starts[pick].astype(jnp.int32), target


def reset(key: jax.Array, scenes: SceneSet, params: EnvParams):
    """Start a random episode -> (Observation, EnvState)."""
    state = start_episode(*sample_episode(key, scenes, params), scenes, params)
    return observe(state, scenes), state


def step_env(state: EnvState, action: jax.Array, scenes: SceneSet, params: EnvParams):
    """One action, no reset -> (obs, state, reward, done, info).

    info: success (Done with the target visible), failed (the move left the agent in
    place), path_len, optimal_len, steps (of the finished or running episode).
    """
    action = jnp.asarray(action, jnp.int32)
    nxt = scenes.next_state[state.scene, state.state, action]
    is_done = action == DONE
    success = is_done & scenes.visible[state.scene, state.state, state.target]
    failed = (nxt == state.state) & ~is_done
    steps = state.steps + 1
    cap = jnp.asarray(params.max_steps, jnp.int32)[scenes.room_type[state.scene]]
    done = is_done | (steps >= cap)
    new = state.replace(
        state=nxt, steps=steps, path_len=state.path_len + (~is_done).astype(jnp.int32),
        prev_action=action, last_failed=failed, revisited=jnp.any(state.trail == nxt),
        trail=state.trail.at[jnp.minimum(steps, state.trail.shape[0] - 1)].set(nxt),
    )
    reward = jnp.where(success, params.success_reward, params.step_penalty).astype(jnp.float32)
    info = {"success": success, "failed": failed, "path_len": new.path_len,
            "optimal_len": state.optimal_len, "steps": steps}
    return observe(new, scenes), new, reward, done, info


def step(key: jax.Array, state: EnvState, action: jax.Array, scenes: SceneSet,
         params: EnvParams):
    """step_env, then a fresh random episode where the old one ended (training)."""
    obs, new, reward, done, info = step_env(state, action, scenes, params)
    obs_r, state_r = reset(key, scenes, params)
    new = jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s), state_r, new)
    obs = jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s), obs_r, obs)
    return obs, new, reward, done, info
