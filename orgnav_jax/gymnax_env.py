"""The navigation environment as a gymnax 1.x `Environment`, with decoded observations.

    from orgnav_jax import gymnax_env
    env, params = gymnax_env.make("small")              # the small benchmark's train rooms
    obs, state = env.reset(key, params)                 # jit / vmap them, as any gymnax env
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

Every gymnax tool then runs on it: `gymnax.wrappers.LogWrapper`,
`FlattenObservationWrapper`, `LegacyStepAPIWrapper` (the five-value API of PureJaxRL),
`GymnaxToDmEnvWrapper`, `GymnaxToGymWrapper` / `GymnaxToVectorGymWrapper` (gymnasium,
for PyTorch agents), `gymnax.experimental.RolloutWrapper`. See docs/environment.md.

- `EnvParams` carries one split's SceneSet as (traced) arrays, plus the step caps, the
  rewards and the minimum start distance as arrays: one compiled step serves every scene
  set of the same shapes and every cap and reward. Only the trail of visited states has
  a static length, `NavEnv.max_steps` (the largest cap an episode may have).
- The rules are orgnav_jax.env's (reset = env.start_episode(env.sample_episode(..)),
  step_env = env.step_env); `step` resets where an episode ended with the same key as
  `orgnav_jax.env.step`, so both give the same numbers for the same key, state and
  action. The state is `orgnav_jax.env.EnvState`.
- Observations are the Baseline's decoded inputs (`models.model_inputs`, the model's own
  feature decoding, under jit): the 7x7xG global feature map, the detections
  (appearance (C, d), boxes (C, 4) in [0, 1], confidences (C,)), the target one-hot (C,)
  and the previous-action one-hot (6,). obs="flat": one float32 vector in that order
  (`OBS_PARTS`; `unflatten` splits it back); obs="dict": the same parts by name.
- Bad input: `make`, `make_params`, `NavEnv` and `GymEnv` check what comes in from Python
  (scene preset, split, obs mode, one step cap per room type, finite rewards; GymEnv.step
  refuses an action outside 0..5); an eager `step` checks its action, state and params.
  Under jit an invalid action or a state outside the params' scenes cannot raise: it is
  a no-op (state unchanged, reward 0, not done) with info["invalid_action"] or
  info["invalid_state"] True, never an alias of a real action.
- terminated: the agent said Done; truncated: another action reached the room type's
  step cap (never both). info keeps orgnav_jax.env's: success, path_len, optimal_len
  (SPL = success * optimal_len / max(path_len, optimal_len)), steps, failed, revisited;
  `step` adds gymnax's final_observation.
"""

from __future__ import annotations

import copy
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
import gymnasium
from gymnax.environments import environment, spaces
from gymnax.wrappers.gym import GymnaxToGymWrapper

from orgnav_jax import env as nav
from orgnav_jax.constants import (
    DEFAULT_SCENE_PRESET, DONE, FEATURE_GRID, NUM_ACTIONS, NUM_CATEGORIES, ROOM_TYPES,
)
from orgnav_jax.models.navmodel import model_inputs
from orgnav_jax.scenes.synthetic.cache import device_split
from orgnav_jax.scenes.sceneset.sceneset import SceneSet

OBS_MODES = ("flat", "dict")
# The observation's parts, in the flat vector's order (ModelInputs' fields but dropout).
OBS_PARTS = ("glob", "app", "box", "conf", "target", "prev_action")


@struct.dataclass(kw_only=True)
class EnvParams(environment.EnvParams):
    """One split's scenes and the rules, all pytree leaves (traced under jit).
    max_steps_in_episode (gymnax's field) is the largest step cap, for tools that read
    it (e.g. RolloutWrapper's default rollout length)."""
    scenes: SceneSet                # a split's SceneSet on the device, info cleared
    step_caps: jax.Array            # (4,) int32 step cap per room type
    success_reward: jax.Array       # () float32
    step_penalty: jax.Array         # () float32
    min_start_dist: jax.Array       # () int32

    def rules(self) -> nav.EnvParams:
        """The orgnav_jax.env settings object with these (possibly traced) values."""
        return nav.EnvParams(success_reward=self.success_reward, step_penalty=self.step_penalty,
                             step_caps=self.step_caps, min_start_dist=self.min_start_dist)


def make_params(scenes: SceneSet, rules: nav.EnvParams | None = None) -> EnvParams:
    """EnvParams for a SceneSet (usually one split's view) and orgnav_jax.env settings
    (default: the training rules, caps 30; EnvParams.evaluation() for the paper's)."""
    if not isinstance(scenes, SceneSet):
        raise TypeError(f"scenes must be a SceneSet, got {type(scenes).__name__}")
    rules = nav.EnvParams() if rules is None else rules
    if not isinstance(rules, nav.EnvParams):
        raise TypeError(f"rules must be an orgnav_jax.env.EnvParams, got {type(rules).__name__}")
    if scenes.num_scenes == 0:
        raise ValueError("the scene set has no rooms (an empty split?)")
    for name in ("success_reward", "step_penalty"):
        value = getattr(rules, name)
        if not np.isfinite(np.asarray(value, np.float64)):
            raise ValueError(f"EnvParams field {name!r}: expected a finite number, got {value!r}")
    if not 0 <= int(rules.min_start_dist) <= 2 ** 31 - 1:
        raise ValueError(f"EnvParams field 'min_start_dist': expected an integer >= 0, got "
                         f"{rules.min_start_dist!r}")
    return EnvParams(
        max_steps_in_episode=int(max(rules.step_caps)),
        # info (preset, seed) is static metadata: cleared, so sets of the same shapes share
        # one compiled step
        scenes=scenes.replace(info=()).to_device(),
        step_caps=jnp.asarray(rules.step_caps, jnp.int32),
        success_reward=jnp.float32(rules.success_reward),
        step_penalty=jnp.float32(rules.step_penalty),
        min_start_dist=jnp.int32(rules.min_start_dist),
    )


def obs_shapes(scenes: SceneSet) -> dict[str, tuple[int, ...]]:
    """The shape of each observation part for a SceneSet's feature widths."""
    G, d, C = scenes.global_dim, scenes.appearance_dim, NUM_CATEGORIES
    return {"glob": (FEATURE_GRID, FEATURE_GRID, G), "app": (C, d), "box": (C, 4),
            "conf": (C,), "target": (C,), "prev_action": (NUM_ACTIONS,)}


# features are unbounded (imported ones may be negative); the rest lie in [0, 1]
_BOUNDS = {"glob": (-np.inf, np.inf), "app": (-np.inf, np.inf)}


def unflatten(flat: jax.Array, scenes: SceneSet) -> dict[str, jax.Array]:
    """A flat observation (..., D) -> its parts by name (the dict observation)."""
    out, i = {}, 0
    for name, shape in obs_shapes(scenes).items():
        n = int(np.prod(shape))
        out[name] = flat[..., i:i + n].reshape(flat.shape[:-1] + shape)
        i += n
    return out


class NavEnv(environment.Environment):
    """Target-driven navigation over a SceneSet, as a gymnax Environment (module doc).

    obs: "flat" or "dict"; max_steps: the trail's capacity, at least every step cap the
    params will hold (a larger cap would let `revisited` miss states beyond it);
    default_params: what `env.default_params` returns (gymnax tools use it when no
    params are given)."""

    def __init__(self, obs: str = "flat", max_steps: int = 30,
                 default_params: EnvParams | None = None):
        super().__init__()
        if obs not in OBS_MODES:
            raise ValueError(f"obs must be one of {list(OBS_MODES)}, got {obs!r}")
        if int(max_steps) < 1:
            raise ValueError(f"max_steps must be >= 1, got {max_steps}")
        self.obs_mode = obs
        self.max_steps = int(max_steps)
        self._default_params = default_params
        if default_params is not None:
            self.check_params(default_params)

    def __deepcopy__(self, memo):
        # gymnasium wrappers deep-copy the env; the default params are immutable device
        # arrays, shared rather than copied
        return copy.copy(self)

    @property
    def default_params(self) -> EnvParams:
        if self._default_params is None:
            raise ValueError("this NavEnv has no default params: pass params (make_params) "
                             "or build it with gymnax_env.make")
        return self._default_params

    def check_params(self, params: EnvParams) -> None:
        """ValueError unless params are this module's EnvParams with one step cap per room
        type (shapes are known under jit too) and, when concrete, caps in
        1..max_steps (the trail's capacity)."""
        if not isinstance(params, EnvParams):
            raise TypeError(f"params must be orgnav_jax.gymnax_env.EnvParams (make_params), "
                            f"got {type(params).__name__}")
        caps = params.step_caps
        if np.shape(caps) != (len(ROOM_TYPES),):
            raise ValueError(f"EnvParams field 'step_caps': expected shape ({len(ROOM_TYPES)},), "
                             f"one cap per room type {list(ROOM_TYPES)}, got shape "
                             f"{tuple(np.shape(caps))}")
        if isinstance(caps, jax.core.Tracer):
            return
        values = np.asarray(caps)
        if not np.issubdtype(values.dtype, np.integer) or values.min() < 1:
            raise ValueError(f"EnvParams field 'step_caps': expected integers >= 1, got "
                             f"{values.tolist()}")
        if int(values.max()) > self.max_steps:
            raise ValueError(f"step caps {values.tolist()} exceed this NavEnv's "
                             f"max_steps {self.max_steps}: build it with max_steps >= the "
                             "largest cap")

    # ------------------------------------------------------------------ the rules
    def reset_env(self, key: jax.Array, params: EnvParams):
        rules = params.rules()
        episode = nav.sample_episode(key, params.scenes, rules)
        state = nav.start_episode(*episode, params.scenes, rules, max_steps=self.max_steps)
        return self.get_obs(state, params), state

    def step_env(self, key: jax.Array, state: nav.EnvState, action, params: EnvParams):
        """One action, no reset (key unused: the transition is deterministic)
        -> (obs, state, reward, terminated, info)."""
        del key
        _, new, reward, _, info = nav.step_env(state, action, params.scenes, params.rules())
        return self.get_obs(new, params), new, reward, info["terminated"], info

    def step(self, key: jax.Array, state: nav.EnvState, action, params: EnvParams | None = None):
        """gymnax's step (auto-reset, six values, info["final_observation"]), resetting
        with `key` itself as orgnav_jax.env.step does (gymnax's base splits it), so both
        give the same episode for the same key. The observation is decoded once, from the
        state kept.

        Bad input: called with concrete values, an action outside 0..5, a state of other
        scenes or malformed params raise ValueError here; under jit (vmap, a wrapper's
        jit) an invalid action or a state outside the params' scenes is a no-op flagged
        in info["invalid_action"] / info["invalid_state"] (orgnav_jax.env's module doc)."""
        params = self.default_params if params is None else params
        self.check_params(params)
        nav.check_action(action)
        nav.check_state(state, params.scenes)
        return self._step(key, state, action, params)

    @partial(jax.jit, static_argnames=("self",))
    def _step(self, key: jax.Array, state: nav.EnvState, action, params: EnvParams):
        obs_st, state_st, reward, terminated, info = self.step_env(key, state, action, params)
        truncated = self.is_truncated(state_st, params)
        done = terminated | truncated
        _, state_re = self.reset_env(key, params)
        state = jax.tree_util.tree_map(lambda r, s: jnp.where(done, r, s), state_re, state_st)
        info = {**info, "terminated": terminated, "truncated": truncated,
                "final_observation": obs_st}
        return self.get_obs(state, params), state, reward, terminated, truncated, info

    def is_terminated(self, state: nav.EnvState, params: EnvParams) -> jax.Array:
        """The last action was Done (orgnav_jax.env's info["terminated"])."""
        return state.prev_action == DONE

    def is_truncated(self, state: nav.EnvState, params: EnvParams) -> jax.Array:
        """The room type's step cap reached by an action other than Done
        (orgnav_jax.env's info["truncated"])."""
        cap = jnp.asarray(params.step_caps, jnp.int32)[params.scenes.room_type[state.scene]]
        return (state.steps >= cap) & (state.prev_action != DONE)

    # ------------------------------------------------------------------ observations
    def decoded(self, state: nav.EnvState, params: EnvParams) -> dict[str, jax.Array]:
        """The model's decoded inputs of a state (models.model_inputs) by part name."""
        inputs = model_inputs(params.scenes, nav.observe(state, params.scenes))
        return {name: getattr(inputs, name) for name in OBS_PARTS}

    def get_obs(self, state: nav.EnvState, params: EnvParams | None = None, key=None):
        params = self.default_params if params is None else params
        parts = self.decoded(state, params)
        if self.obs_mode == "dict":
            return parts
        lead = state.state.shape
        return jnp.concatenate([parts[k].reshape(lead + (-1,)) for k in OBS_PARTS], axis=-1)

    # ------------------------------------------------------------------ spaces
    @property
    def name(self) -> str:
        return "OrgNav"

    @property
    def num_actions(self) -> int:
        return NUM_ACTIONS

    def action_space(self, params: EnvParams | None = None) -> spaces.Discrete:
        return spaces.Discrete(NUM_ACTIONS)

    def observation_space(self, params: EnvParams | None = None):
        params = self.default_params if params is None else params
        shapes = obs_shapes(params.scenes)
        boxes = {k: spaces.Box(*_BOUNDS.get(k, (0.0, 1.0)), shape, np.float32)
                 for k, shape in shapes.items()}
        if self.obs_mode == "dict":
            return spaces.Dict(boxes)
        low = np.concatenate([np.full(int(np.prod(s)), _BOUNDS.get(k, (0.0, 1.0))[0], np.float32)
                              for k, s in shapes.items()])
        high = np.concatenate([np.full(int(np.prod(s)), _BOUNDS.get(k, (0.0, 1.0))[1], np.float32)
                               for k, s in shapes.items()])
        return spaces.Box(low, high, (low.size,), np.float32)


class GymEnv(GymnaxToGymWrapper):
    """gymnax's GymnaxToGymWrapper with the two things gymnasium's env_checker asks for
    and gymnax 1.0.1's wrapper lacks (for any gymnax env, CartPole too): reset(seed=...)
    also seeds gymnasium's np_random, and observations, rewards and flags come back as
    numpy (jax arrays cannot be compared by the checker's determinism test). A single
    environment on the host, one jitted step per call; for batches use gymnax's
    GymnaxToVectorGymWrapper (docs/environment.md)."""

    def reset(self, *, seed: int | None = None, options=None, **kw):
        gymnasium.Env.reset(self, seed=seed)
        obs, info = super().reset(seed=seed, options=options)
        return _to_numpy(obs), info

    def __init__(self, env: NavEnv, params: EnvParams | None = None, seed: int | None = None):
        params = env.default_params if params is None else params
        env.check_params(params)
        super().__init__(env, params, seed)

    def step(self, action):
        """One action (an integer in 0..5; anything else is a ValueError, not an alias)."""
        nav.check_action(action)
        obs, reward, terminated, truncated, info = super().step(action)
        return (_to_numpy(obs), float(reward), bool(terminated), bool(truncated),
                _to_numpy(info))


def _to_numpy(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def make(scene_preset: str = DEFAULT_SCENE_PRESET, split: str = "train", obs: str = "flat", *,
         seed: int = 0, scenes_dir: str | None = None, scenes: SceneSet | None = None,
         rules: nav.EnvParams | None = None, max_steps: int | None = None
         ) -> tuple[NavEnv, EnvParams]:
    """(NavEnv, its EnvParams) for one split of a scene set.

    scene_preset / seed: a cached preset (built once, as the trainer does); scenes_dir:
    a saved SceneSet instead; scenes: a SceneSet given directly (then scene_preset, seed
    and scenes_dir are not used). split: "train", "val" or "test". obs: "flat" or
    "dict". rules: orgnav_jax.env.EnvParams (default: training caps 30;
    EnvParams.evaluation() for the paper's 100/200). max_steps: the trail's capacity
    (default: the largest cap), raise it to use larger caps with the same env later.
    """
    rules = nav.EnvParams() if rules is None else rules
    if obs not in OBS_MODES:            # before a scene set is built or loaded
        raise ValueError(f"obs must be one of {list(OBS_MODES)}, got {obs!r}")
    if split not in ("train", "val", "test"):
        raise ValueError(f"split must be one of ['train', 'val', 'test'], got {split!r}")
    if max_steps is not None and (not isinstance(max_steps, (int, np.integer))
                                  or isinstance(max_steps, bool) or max_steps < 1):
        raise ValueError(f"max_steps must be an integer >= 1, got {max_steps!r}")
    rooms = (scenes.split_view(split) if scenes is not None
             else device_split(scene_preset, seed, scenes_dir, split))  # one device copy
    params = make_params(rooms, rules)
    steps = max(rules.step_caps) if max_steps is None else max_steps
    return NavEnv(obs=obs, max_steps=steps, default_params=params), params
