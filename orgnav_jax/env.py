"""The navigation environment as pure functions (gymnax style), for vmap and jit.

    obs, state = reset(key, scenes, params)
    obs, state, reward, done, info = step(key, state, action, scenes, params)  # auto-reset
    obs, state, reward, done, info = step_env(state, action, scenes, params)  # no reset

`scenes` is a SceneSet (usually one split's view, moved to device); `params` is a static
EnvParams. All shapes below are per environment; vmap adds the batch axis in front.

State indices: EnvState.state, its trail and Observation.state are GLOBAL indices into
the SceneSet's flat state axis (the per-state arrays are indexed by them directly);
episodes are given and sampled with a room's LOCAL start index (as episode files store
it), converted by start_episode: global = scenes.state_offset[scene] + local.

Path lengths count the moving actions (MoveAhead, Rotate*, Look*), not the final Done:
an episode's L is its number of non-Done steps and L_opt = scenes.dist at the start, so
the expert has L = L_opt and SPL 1.

Bad input. Called eagerly (concrete values), step and step_env raise ValueError for an
action that is not an integer in 0..5 and for a state outside `scenes` (check_action,
check_state). Under jit a value cannot raise; there an invalid action (-1, 7, 2.7, nan)
or a state whose scene or state index lies outside `scenes` (a state of another scene
set) is a no-op: the state comes back unchanged, reward 0, done False (no auto-reset),
and info["invalid_action"] / info["invalid_state"] is True. Such an action is never
aliased to a real one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from orgnav_jax.constants import ACTIONS, CATEGORIES, DONE, NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES
from orgnav_jax.scenes.sceneset.sceneset import SceneSet

START_TRIES = 4  # start states drawn per reset; the first with a valid target is kept


@struct.dataclass
class EnvParams:
    """Static settings (hashable, so jit specializes on them)."""
    success_reward: float = struct.field(pytree_node=False, default=5.0)
    step_penalty: float = struct.field(pytree_node=False, default=-0.01)  # paper: -0.001
    step_caps: tuple[int, ...] = struct.field(pytree_node=False, default=(30, 30, 30, 30))
    min_start_dist: int = struct.field(pytree_node=False, default=1)

    def __post_init__(self):
        """One step cap per room type (fewer would make the last cap serve the others):
        their number is checked always (also for the traced arrays gymnax_env passes),
        their values when they are Python numbers."""
        caps = self.step_caps
        if isinstance(caps, list):
            object.__setattr__(self, "step_caps", caps := tuple(caps))
        n = len(caps) if isinstance(caps, tuple) else np.shape(caps)
        if n != len(ROOM_TYPES) and n != (len(ROOM_TYPES),):
            raise ValueError(f"EnvParams field 'step_caps': expected {len(ROOM_TYPES)} caps, "
                             f"one per room type {list(ROOM_TYPES)}, got {caps!r}")
        if isinstance(caps, tuple) and not all(
                isinstance(c, (int, np.integer)) and not isinstance(c, bool) and
                1 <= c <= 2 ** 31 - 2 for c in caps):
            raise ValueError(f"EnvParams field 'step_caps': expected integers >= 1, got "
                             f"{list(caps)}")

    @classmethod
    def evaluation(cls, **kw) -> EnvParams:
        """The paper's evaluation caps: 100 steps, 200 in living rooms."""
        caps = tuple(200 if t == "living_room" else 100 for t in ROOM_TYPES)
        return cls(step_caps=caps, **kw)


@struct.dataclass
class EnvState:
    scene: jax.Array        # () int32 index into the SceneSet
    state: jax.Array        # () int32 GLOBAL flat state index (a state of that scene)
    target: jax.Array       # () int32 category index
    steps: jax.Array        # () int32 actions taken this episode (Done included)
    path_len: jax.Array     # () int32 non-Done actions taken
    prev_action: jax.Array  # () int32, -1 at episode start
    last_failed: jax.Array  # () bool: the last action left the agent where it was
    revisited: jax.Array    # () bool: the current state was visited before this episode
    trail: jax.Array        # (T+1,) int32 global states visited this episode, -1 beyond;
                            #   T = max cap
    optimal_len: jax.Array  # () int32 shortest path length at the start


@struct.dataclass
class Observation:
    scene: jax.Array        # () int32 scene index
    state: jax.Array        # () int32 global flat state: the index of the large features
    det_box: jax.Array      # (C, 4) float32 box in pixels (x1, y1, x2, y2), 0 if none
    det_conf: jax.Array     # (C,) float32 confidence, 0 = no detection
    target: jax.Array       # (C,) float32 one-hot target category
    prev_action: jax.Array  # (A,) float32 one-hot previous action, zeros at start
    deadlock: jax.Array     # () bool: revisited state or failed last action


def observe(state: EnvState, scenes: SceneSet) -> Observation:
    """The observation of an EnvState (gathers the small per-state arrays)."""
    return Observation(
        scene=state.scene, state=state.state,
        det_box=scenes.det_box[state.state].astype(jnp.float32),
        det_conf=scenes.det_conf[state.state].astype(jnp.float32),
        target=jax.nn.one_hot(state.target, NUM_CATEGORIES),
        prev_action=jax.nn.one_hot(state.prev_action, NUM_ACTIONS),
        deadlock=state.last_failed | state.revisited,
    )


def _concrete(x) -> bool:
    """True when x is a concrete value (eager call), False under jit/vmap tracing."""
    return not isinstance(x, jax.core.Tracer)


def check_action(action) -> None:
    """Eager calls: a clear error for an action outside 0..5 (or not an integer). Under
    jit values are not known: there an invalid action is a no-op flagged in
    info["invalid_action"] (action_is_valid, step_env)."""
    if _concrete(action):
        a = np.asarray(action)
        if not np.issubdtype(a.dtype, np.integer) or a.size and (a.min() < 0 or a.max() >= NUM_ACTIONS):
            raise ValueError(f"action {a.tolist()} invalid: expected integers in 0..{NUM_ACTIONS - 1} "
                             f"({', '.join(ACTIONS)})")


def action_is_valid(action) -> jax.Array:
    """True where `action` is one of the actions 0..5: an integer in range, or a float
    with an integral value in range (2.0 yes, 2.7, -1, 7, nan no; booleans never)."""
    a = jnp.asarray(action)
    if a.dtype == jnp.bool_:
        return jnp.zeros(a.shape, bool)
    ok = (a >= 0) & (a < NUM_ACTIONS)
    if not jnp.issubdtype(a.dtype, jnp.integer):
        ok = ok & (a == jnp.floor(a))
    return ok


def state_is_valid(state: EnvState, scenes: SceneSet) -> jax.Array:
    """True where an EnvState can belong to `scenes`: its scene index is one of theirs and
    its (global) state lies in that room's range. A state of another scene set whose
    indices happen to fall in range cannot be told apart."""
    n = scenes.state_offset.shape[0]
    scene = jnp.clip(state.scene, 0, n - 1)
    lo = scenes.state_offset[scene]
    return ((state.scene >= 0) & (state.scene < n) & (state.state >= lo)
            & (state.state < lo + scenes.state_count[scene]))


def check_state(state: EnvState, scenes: SceneSet) -> None:
    """Eager calls: a clear error for an EnvState whose scene or state index is outside
    `scenes` (a state of another scene set); under jit see state_is_valid."""
    if _concrete(state.scene) and _concrete(state.state):
        ok = np.asarray(state_is_valid(state, scenes))
        if not ok.all():
            raise ValueError(
                f"env state (scene {np.asarray(state.scene).tolist()}, state "
                f"{np.asarray(state.state).tolist()}) is not a state of these scenes "
                f"({scenes.num_scenes} rooms, {int(scenes.num_states)} states): a state of "
                "another scene set?")


def check_episode(scene, start, target, scenes: SceneSet) -> None:
    """Eager calls: clear errors for a scene, (local) start state or target the SceneSet
    lacks."""
    if not all(_concrete(x) for x in (scene, start, target)):
        return
    n, s, c = (int(np.asarray(x)) for x in (scene, start, target))
    if not 0 <= n < scenes.num_scenes:
        raise ValueError(f"scene index {n} outside 0..{scenes.num_scenes - 1}")
    name = scenes.scene_names[n]
    if not 0 <= s < int(scenes.state_count[n]):
        raise ValueError(f"start state {s} is not a state of {name} "
                         f"(it has {int(scenes.state_count[n])})")
    if not 0 <= c < NUM_CATEGORIES or not bool(scenes.targets[n, c]):
        valid = [CATEGORIES[i] for i in np.flatnonzero(np.asarray(scenes.targets[n]))]
        what = CATEGORIES[c] if 0 <= c < NUM_CATEGORIES else f"index {c}"
        raise ValueError(f"target {what} is not a valid target of {name} (absent or never "
                         f"visible); valid targets: {valid}")


def start_episode(scene: jax.Array, start: jax.Array, target: jax.Array,
                  scenes: SceneSet, params: EnvParams, max_steps: int | None = None) -> EnvState:
    """The EnvState at the start of a given episode (scene, LOCAL start state index in
    that room, as in an EpisodeSet, target); EnvState.state is the global flat index.

    The visited set is a trail of at most max_steps + 1 states: far smaller than a bitset
    over S, and an any() over it is cheap. max_steps (static) defaults to
    max(params.step_caps); gymnax_env passes it, its step caps being traced arrays.
    """
    check_episode(scene, start, target, scenes)
    state = (scenes.state_offset[scene] + start).astype(jnp.int32)
    steps = max(params.step_caps) if max_steps is None else max_steps
    trail = jnp.full(steps + 1, -1, jnp.int32).at[0].set(state)
    return EnvState(
        scene=scene, state=state, target=target, steps=jnp.int32(0), path_len=jnp.int32(0),
        prev_action=jnp.int32(-1), last_failed=jnp.bool_(False), revisited=jnp.bool_(False),
        trail=trail,
        optimal_len=scenes.dist[state, target].astype(jnp.int32),
    )


def sample_episode(key: jax.Array, scenes: SceneSet, params: EnvParams):
    """A random (scene, local start, target) -> three () int32 (start_episode's inputs).

    A scene uniformly; START_TRIES start states uniformly among its states, keeping the
    first from which some valid target is at least params.min_start_dist away; a target
    uniformly among those. (If every try sees every target, the last try is kept and
    the target drawn among all valid ones; with 4 tries this is vanishingly rare.)
    Draws START_TRIES + 2 random words in one call; no categorical sampling, so it is
    cheap enough to run on every auto-reset step.
    """
    bits = jax.random.bits(key, (START_TRIES + 2,), jnp.uint32)
    scene = (bits[0] % jnp.uint32(scenes.num_scenes)).astype(jnp.int32)
    starts = (bits[1:START_TRIES + 1] % scenes.state_count[scene].astype(jnp.uint32)
              ).astype(jnp.int32)                                          # (T,)
    valid = scenes.targets[scene]                                          # (C,)
    far = scenes.dist[scenes.state_offset[scene] + starts] >= params.min_start_dist  # (T, C)
    ok = valid[None] & far
    has = ok.any(1)
    pick = jnp.where(has.any(), jnp.argmax(has), START_TRIES - 1)
    allowed = jnp.where(has.any(), ok[pick], valid)
    count = allowed.sum().astype(jnp.uint32)
    k = (bits[START_TRIES + 1] % jnp.maximum(count, 1)).astype(jnp.int32)
    target = jnp.argmax(jnp.cumsum(allowed) > k).astype(jnp.int32)        # k-th allowed
    return scene, starts[pick], target


def reset(key: jax.Array, scenes: SceneSet, params: EnvParams):
    """Start a random episode -> (Observation, EnvState)."""
    state = start_episode(*sample_episode(key, scenes, params), scenes, params)
    return observe(state, scenes), state


def _transition(state: EnvState, action: jax.Array, scenes: SceneSet, params: EnvParams):
    """One action -> (new state, reward, done, info); see step_env."""
    check_action(action)
    check_state(state, scenes)
    ok_action = action_is_valid(action)
    ok_state = state_is_valid(state, scenes)
    valid = ok_action & ok_state
    action = jnp.where(ok_action, action, 0).astype(jnp.int32)
    nxt = scenes.next_state[state.state, action]
    is_done = (action == DONE) & valid
    success = is_done & scenes.visible[state.state, state.target]
    failed = (nxt == state.state) & ~is_done & valid
    steps = state.steps + 1
    cap = jnp.asarray(params.step_caps, jnp.int32)[scenes.room_type[state.scene]]
    truncated = (steps >= cap) & ~is_done & valid
    done = is_done | truncated
    # an invalid action or a state of other scenes: nothing happens (module doc). The
    # scalars are selected; the trail is written at an index past its end when the step
    # is invalid, which the scatter drops (no select over the whole trail per step).
    keep = lambda a, b: jnp.where(valid, a, b)
    last = state.trail.shape[0]
    new = state.replace(
        state=keep(nxt, state.state), steps=keep(steps, state.steps),
        path_len=keep(state.path_len + (~is_done).astype(jnp.int32), state.path_len),
        prev_action=keep(action, state.prev_action),
        last_failed=keep(failed, state.last_failed),
        revisited=keep(jnp.where(is_done, state.revisited, jnp.any(state.trail == nxt)),
                       state.revisited),
        trail=state.trail.at[jnp.where(valid, jnp.minimum(steps, last - 1), last)].set(
            nxt, mode="drop"),
    )
    reward = jnp.where(success, params.success_reward, params.step_penalty).astype(jnp.float32)
    reward = jnp.where(valid, reward, jnp.float32(0))
    info = {"success": success, "failed": failed, "path_len": new.path_len,
            "optimal_len": state.optimal_len, "steps": new.steps,
            "revisited": new.revisited & ~is_done & valid, "terminated": is_done,
            "truncated": truncated, "invalid_action": ~ok_action, "invalid_state": ~ok_state}
    return new, reward, done, info


def step_env(state: EnvState, action: jax.Array, scenes: SceneSet, params: EnvParams):
    """One action, no reset -> (obs, state, reward, done, info).

    done = info["terminated"] | info["truncated"], never both (gymnax, xland-minigrid):
    terminated: the agent said Done; truncated: another action reached the room type's
    step cap. info also has success (Done with the target visible), failed (the move
    left the agent in place), revisited (a non-Done action led to a state visited before
    in the episode; failed moves included), path_len, optimal_len, steps (of the
    finished or running episode). Training treats both ends alike (no bootstrap past
    either); the loss does not look at which.
    """
    new, reward, done, info = _transition(state, action, scenes, params)
    return observe(new, scenes), new, reward, done, info


def step(key: jax.Array, state: EnvState, action: jax.Array, scenes: SceneSet,
         params: EnvParams):
    """step_env, then a fresh random episode where the old one ended (training).
    reward, done and info describe the action taken; obs and state the next episode."""
    new, reward, done, info = _transition(state, action, scenes, params)
    fresh = start_episode(*sample_episode(key, scenes, params), scenes, params)
    new = jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s), fresh, new)
    return observe(new, scenes), new, reward, done, info
