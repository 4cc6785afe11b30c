"""The evaluation protocol: fixed episodes, greedy actions, success / SPL / L>=5 metrics.

    policy = random_policy()            # or expert_policy(), or a trained model's policy
    result = evaluate(policy, None, scenes, episodes, EnvParams.evaluation())
    print(format_table({"Random": result["overall"]}))

A Policy is a pair of pure, batched functions:
    init(batch, policy_params)                          -> carry (pytree, leading axis B)
    act(policy_params, carry, obs, key, scenes, fresh)  -> (actions (B,) int32, carry)
`obs` is a batched env.Observation; `fresh` (B,) bool is True on an episode's first step
(recurrent policies reset their memory there). Every episode runs to Done or its cap
(params.step_caps by room type) in one jitted lax.scan, vmapped over a batch.

Metrics per episode: success; SPL = success * L_opt / max(L, L_opt), where L counts the
non-Done actions and L_opt the shortest such path at the start; "L>=5" keeps the
episodes with L_opt >= 5.

Failure analysis, counted inside the scan (docs/evaluation.md): every episode ends in
exactly one of success (Done with the target visible), wrong_done (Done with the target
not visible) and timeout (the step cap reached without Done). revisits counts the
non-Done steps that moved the agent to another state it had visited before in the
episode; failed_moves the non-Done steps that left it in place (a blocked MoveAhead,
LookUp at horizon 0, LookDown at 30). The two are disjoint: their sum is the number of
steps after which the env flags a deadlock (Observation.deadlock).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from orgnav_jax import env
from orgnav_jax.compile_cache import compiled_once
from orgnav_jax.constants import CATEGORIES, NUM_ACTIONS, ROOM_TYPES
from orgnav_jax.episodes import EpisodeSet
from orgnav_jax.models.navmodel import check_feature_widths, feature_widths
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.tree import where_rows

LONG_PATH = 5  # the paper's "L>=5" columns
OUTCOMES = ("success", "wrong_done", "timeout")  # per-episode flags, a partition
COUNTS = ("revisits", "failed_moves")            # per-episode step counts
FAILURE_KEYS = OUTCOMES[1:] + COUNTS             # what summarize adds when present


@dataclasses.dataclass(frozen=True)
class Policy:
    """Batched policy functions (see module docstring); `name` is for tables."""
    name: str
    init: Callable[[int, Any], Any]
    act: Callable[..., tuple[jax.Array, Any]]
    # record(carry) -> dict of (B,) arrays kept per step by trace_episodes (e.g. TPN's
    # update count); None: nothing beyond the env's trace
    record: Callable[[Any], dict] | None = None


@compiled_once
def random_policy() -> Policy:
    """Uniform over the 6 actions (Done included), as the paper's Random row."""
    def act(_, carry, obs, key, scenes, fresh):
        return jax.random.randint(key, obs.state.shape, 0, NUM_ACTIONS), carry
    return Policy("Random", lambda batch, _: (), act)


@compiled_once
def expert_policy() -> Policy:
    """The shortest-path expert: scenes.expert_action for the observed target."""
    def act(_, carry, obs, key, scenes, fresh):
        target = jnp.argmax(obs.target, axis=-1)
        return scenes.expert_action[obs.state, target].astype(jnp.int32), carry
    return Policy("Expert", lambda batch, _: (), act)


@functools.partial(jax.jit, static_argnames=("policy", "params", "num_steps", "trace"))
def _run_batch(policy: Policy, policy_params, scenes: SceneSet, scene, start, target,
               key, params: env.EnvParams, num_steps: int, trace: bool = False):
    """Episodes (B,) -> dict of (B,) arrays: success, wrong_done, timeout (bool),
    path_len, steps, revisits, failed_moves (int32), finished (bool); with trace=True
    also "trace": per-step (num_steps, B) arrays: state (before the step), action,
    deadlock, running, and the policy's record(carry)."""
    batch = scene.shape[0]
    state = jax.vmap(env.start_episode, in_axes=(0, 0, 0, None, None))(
        scene, start, target, scenes, params)
    obs = jax.vmap(env.observe, in_axes=(0, None))(state, scenes)
    v_step = jax.vmap(env.step_env, in_axes=(0, 0, None, None))

    def body(carry, key):
        state, obs, pcarry, running, fresh, c = carry
        action, pcarry = policy.act(policy_params, pcarry, obs, key, scenes, fresh)
        obs2, state2, _, done, info = v_step(state, action, scenes, params)
        moved_back = info["revisited"] & ~info["failed"]   # env: non-Done, visited before
        c = {"success": c["success"] | (running & info["success"]),
             "wrong_done": c["wrong_done"] | (running & info["terminated"] & ~info["success"]),
             "timeout": c["timeout"] | (running & info["truncated"]),
             "revisits": c["revisits"] + (running & moved_back).astype(jnp.int32),
             "failed_moves": c["failed_moves"] + (running & info["failed"]).astype(jnp.int32)}
        record = None
        if trace:
            record = {"state": state.state, "action": action, "deadlock": obs.deadlock,
                      "running": running, **(policy.record(pcarry) if policy.record else {})}
        state, obs = where_rows(running, (state2, obs2), (state, obs))
        return (state, obs, pcarry, running & ~done, jnp.zeros_like(fresh), c), record

    flag, count = jnp.zeros(batch, bool), jnp.zeros(batch, jnp.int32)
    counters = {"success": flag, "wrong_done": flag, "timeout": flag,
                "revisits": count, "failed_moves": count}
    init = (state, obs, policy.init(batch, policy_params), jnp.ones(batch, bool),
            jnp.ones(batch, bool), counters)
    (state, _, _, running, _, c), steps = jax.lax.scan(
        body, init, jax.random.split(key, num_steps))
    out = {**c, "path_len": state.path_len, "steps": state.steps, "finished": ~running}
    return dict(out, trace=steps) if trace else out


def trace_episodes(policy: Policy, policy_params, scenes: SceneSet, episodes: EpisodeSet,
                   params: env.EnvParams, seed: int = 0) -> dict[str, np.ndarray]:
    """A few episodes step by step (one batch of the evaluation scan) -> numpy arrays:
    the outcome per episode (E,) as run_episodes, and per step (E, T, ...): state (the
    flat state before the step), action, deadlock, running, and what policy.record keeps
    (its trailing axes too)."""
    check_scenes(policy, policy_params, scenes)
    arrays = [jnp.asarray(a) for a in (episodes.scene, episodes.start, episodes.target)]
    res = _run_batch(policy, policy_params, scenes, *arrays, jax.random.PRNGKey(seed),
                     params, max(params.step_caps), trace=True)
    out = {k: np.asarray(v) for k, v in res.items() if k != "trace"}
    out.update({k: np.swapaxes(np.asarray(v), 0, 1) for k, v in res["trace"].items()})
    return out


def check_scenes(policy: Policy, policy_params, scenes: SceneSet) -> None:
    """A model's parameters fit only scenes with the feature widths it was trained on
    (models.feature_widths): ValueError naming both before anything is compiled."""
    if policy_params is None:
        return
    preset = scenes.meta("preset")
    name = f"({scenes.num_scenes} rooms{f' of preset {preset!r}' if preset else ''})"
    check_feature_widths(feature_widths(policy_params), scenes, f"policy {policy.name}", name)


def run_episodes(policy: Policy, policy_params, scenes: SceneSet, episodes: EpisodeSet,
                 params: env.EnvParams, seed: int = 0, batch_size: int = 1000,
                 progress: Callable[[int], None] | None = None) -> dict[str, np.ndarray]:
    """Run every episode to its end -> per-episode numpy arrays (E,): success, wrong_done,
    timeout (bool; exactly one is true per episode), path_len, steps, revisits,
    failed_moves, optimal_len, spl, room_type, target. Batches are padded to batch_size
    so the jitted scan compiles once."""
    num_steps = max(params.step_caps)
    n = len(episodes)
    if n == 0:
        raise ValueError("no episodes to evaluate (an empty episode set)")
    if batch_size < 1:
        raise ValueError(f"batch_size {batch_size}, expected an integer >= 1")
    check_scenes(policy, policy_params, scenes)
    out: dict[str, list] = {k: [] for k in (*OUTCOMES, "path_len", "steps", *COUNTS)}
    key = jax.random.PRNGKey(seed)
    for lo in range(0, n, batch_size):
        idx = np.arange(lo, lo + batch_size) % n       # pad the last batch by wrapping
        arrays = [jnp.asarray(a[idx]) for a in (episodes.scene, episodes.start,
                                                episodes.target)]
        res = _run_batch(policy, policy_params, scenes, *arrays, jax.random.fold_in(key, lo),
                         params, num_steps)
        if not bool(np.asarray(res["finished"]).all()):
            raise RuntimeError("an episode outlived its cap; EnvParams.step_caps is inconsistent")
        keep = min(batch_size, n - lo)
        for k in out:
            out[k].append(np.asarray(res[k])[:keep])
        if progress:
            progress(keep)
    result = {k: np.concatenate(v) for k, v in out.items()}
    L, L_opt = result["path_len"], episodes.optimal_len
    result["optimal_len"] = np.asarray(L_opt)
    result["spl"] = spl(result["success"], L, L_opt)
    result["room_type"] = np.asarray(episodes.room_type)
    result["target"] = np.asarray(episodes.target)
    return result


def spl(success, path_len, optimal_len) -> np.ndarray:
    """Per-episode SPL = S * L_opt / max(L, L_opt); where both lengths are 0 (a start that
    sees its target, Done at once: the optimal path) it is S, as the release's count of
    states gives ((L_opt + 1) / (L + 1) = 1)."""
    success, L, L_opt = (np.asarray(a, np.float64) for a in (success, path_len, optimal_len))
    longest = np.maximum(L, L_opt)
    return np.where(longest > 0, success * L_opt / np.maximum(longest, 1), success)


def summarize(per_episode: dict[str, np.ndarray]) -> dict[str, float]:
    """Mean success and SPL over all episodes and over those with L_opt >= 5; where the
    per-episode arrays have them (run_episodes does), the failure analysis over all
    episodes: the shares wrong_done and timeout (with success they sum to 1) and the
    mean revisits and failed_moves per episode."""
    long = per_episode["optimal_len"] >= LONG_PATH
    mean = lambda a, m: float(np.mean(a[m])) if m.any() else float("nan")
    every = np.ones_like(long)
    out = {"episodes": int(long.size), "success": mean(per_episode["success"], every),
           "spl": mean(per_episode["spl"], every), "episodes_L5": int(long.sum()),
           "success_L5": mean(per_episode["success"], long),
           "spl_L5": mean(per_episode["spl"], long)}
    for k in FAILURE_KEYS:
        if k in per_episode:
            out[k] = mean(np.asarray(per_episode[k], np.float64), every)
    return out


# what a results JSON keeps of every episode (its "per_episode" part): enough to recompute
# every summary and to pair two policies episode by episode (experiments/claims.py)
EPISODE_FIELDS = ("outcome", "path_len", "optimal_len", "revisits", "failed_moves",
                  "room_type", "target")


def episode_record(per_episode: dict[str, np.ndarray]) -> dict[str, list[int]]:
    """run_episodes' arrays -> {field: list of ints (E,)} for EPISODE_FIELDS; outcome is
    the index into OUTCOMES (0 success, 1 wrong_done, 2 timeout)."""
    outcome = np.argmax(np.stack([np.asarray(per_episode[k]) for k in OUTCOMES]), axis=0)
    return {k: np.asarray(outcome if k == "outcome" else per_episode[k]).astype(int).tolist()
            for k in EPISODE_FIELDS}


def episodes_from_record(record: dict[str, list[int]]) -> dict[str, np.ndarray]:
    """episode_record's lists -> the arrays summarize/metrics read (the inverse)."""
    out = {k: np.asarray(record[k], np.int64) for k in EPISODE_FIELDS if k != "outcome"}
    outcome = np.asarray(record["outcome"], np.int64)
    out.update({k: outcome == i for i, k in enumerate(OUTCOMES)})
    out["spl"] = spl(out["success"], out["path_len"], out["optimal_len"])
    return out


def metrics(per_episode: dict[str, np.ndarray]) -> dict:
    """{"overall", "per_room_type", "per_target"} summaries (see summarize)."""
    def part(mask):
        return summarize({k: v[mask] for k, v in per_episode.items()})
    out = {"overall": summarize(per_episode), "per_room_type": {}, "per_target": {}}
    for t, name in enumerate(ROOM_TYPES):
        m = per_episode["room_type"] == t
        if m.any():
            out["per_room_type"][name] = part(m)
    for c, name in enumerate(CATEGORIES):
        m = per_episode["target"] == c
        if m.any():
            out["per_target"][name] = part(m)
    return out


def evaluate(policy: Policy, policy_params, scenes: SceneSet, episodes: EpisodeSet,
             params: env.EnvParams | None = None, seed: int = 0, batch_size: int = 1000,
             progress: Callable[[int], None] | None = None) -> dict:
    """run_episodes + metrics -> {"overall", "per_room_type", "per_target",
    "per_episode" (episode_record: every episode's outcome and lengths, in order)}."""
    params = params or env.EnvParams.evaluation()
    per_episode = run_episodes(policy, policy_params, scenes, episodes, params, seed,
                               min(batch_size, len(episodes)), progress)
    return dict(metrics(per_episode), per_episode=episode_record(per_episode))


def format_table(rows: dict[str, dict], title: str = "") -> str:
    """A Table-1-style text table: one row per method, columns ALL (Success, SPL) and
    L>=5 (Success, SPL), in percent."""
    head = f"{'Method':<22} {'ALL':^17} {'L>=5':^17}\n{'':<22} {'Success':>8} {'SPL':>8} " \
           f"{'Success':>8} {'SPL':>8}"
    lines = [title] if title else []
    lines += [head, "-" * len(head.splitlines()[-1])]
    for name, m in rows.items():
        lines.append(f"{name:<22} {100 * m['success']:8.1f} {100 * m['spl']:8.1f} "
                     f"{100 * m['success_L5']:8.1f} {100 * m['spl_L5']:8.1f}")
    return "\n".join(lines)


def format_failures(rows: dict[str, dict], title: str = "") -> str:
    """The failure analysis as a text table: one row per method (or room type), columns
    Success, wrong Done, Timeout (percent of episodes, summing to 100), revisits and
    failed moves per episode; '-' where a summary lacks the keys (older results)."""
    head = (f"{'Method':<22} {'Success':>8} {'WrongDone':>9} {'Timeout':>8} {'Revisits':>9} "
            f"{'FailedMv':>9}\n{'':<22} {'%':>8} {'%':>9} {'%':>8} {'/ep':>9} {'/ep':>9}")
    lines = [title] if title else []
    lines += [head, "-" * len(head.splitlines()[0])]
    for name, m in rows.items():
        cells = [f"{100 * m['success']:8.1f}"]
        for k, w, scale in (("wrong_done", 9, 100), ("timeout", 8, 100), ("revisits", 9, 1),
                            ("failed_moves", 9, 1)):
            cells.append(f"{scale * m[k]:{w}.1f}" if k in m else f"{'-':>{w}}")
        lines.append(f"{name:<22} " + " ".join(cells))
    return "\n".join(lines)
