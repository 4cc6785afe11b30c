"""One episode from above, and the TPN memory's attention over an episode (Fig. 3)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orgnav_jax import api, env, evaluation
from orgnav_jax.constants import ACTIONS, CATEGORIES, EPISODES_PER_ROOM_TYPE
from orgnav_jax.episodes import load_episodes, sample_episodes
from orgnav_jax.errors import UserError
from orgnav_jax.plots.common import pyplot, save_png
from orgnav_jax.scenes import device_split


def trace_run_episode(run_dir: str | Path, episode: int = 0, split: str = "test",
                      episodes_file: str | None = None, episode_seed: int = 0,
                      per_room_type: int | None = None, test_time: dict | None = None) -> dict:
    """One episode of a run's policy (a training run, or a TPN run with its test-time
    updates; `test_time` overrides their fields, as evaluate's --when, --target, ...),
    step by step -> {"trace": evaluation.trace_episodes of it, "scenes": the split's
    SceneSet, "episode": the one-episode EpisodeSet, "name": the policy, "outcome": one of
    evaluation.OUTCOMES, "steps": the T steps the episode took, (T,) arrays of the trace
    (state, action, deadlock, ...; a TPN run adds "updated", the steps the test-time
    update took, and "tpn_attention" (T, T))}.
    The episode is number `episode` of the split's seeded set (as evaluate samples it),
    or of `episodes_file`."""
    loaded = api.load_run(run_dir, **(test_time or {}))
    scenes = device_split(loaded.scene_preset, loaded.scene_seed, loaded.scenes_dir, split)
    episodes = (load_episodes(episodes_file, scenes) if episodes_file else
                sample_episodes(scenes, per_room_type or EPISODES_PER_ROOM_TYPE,
                                seed=episode_seed, split=split))
    if not 0 <= episode < len(episodes):
        raise ValueError(f"--episode {episode}: the {split} set has episodes 0..."
                         f"{len(episodes) - 1}")
    one = episodes.subset(np.array([episode]))
    trace = evaluation.trace_episodes(loaded.policy, loaded.params, scenes, one,
                                      env.EnvParams.evaluation())
    T = int(trace["running"][0].sum())          # running: True on the steps taken
    steps = {k: v[0][:T] for k, v in trace.items() if v.ndim >= 2}
    if "tpn_updates" in steps:
        steps["updated"] = np.diff(steps["tpn_updates"], prepend=0) > 0
    if "tpn_attention" in steps:
        steps["tpn_attention"] = steps["tpn_attention"][:, :T]
    return {"trace": trace, "scenes": scenes, "episode": one, "name": loaded.policy.name,
            "outcome": next(k for k in evaluation.OUTCOMES if trace[k][0]), "steps": steps}


def plot_episode(run_dir: str | Path, episode: int = 0, split: str = "test",
                 out: str | Path | None = None, **kw) -> Path:
    """Top view of one episode of a run (trace_run_episode): the room's positions, where
    the target is in view, the agent's path from start to end, its deadlock steps and the
    steps where TPN updated the policy -> the PNG path (default RUN_DIR/episode-K.png)."""
    plt = pyplot()
    got = trace_run_episode(run_dir, episode, split, **kw)
    steps, scenes, one, outcome = got["steps"], got["scenes"], got["episode"], got["outcome"]
    n, target = int(one.scene[0]), int(one.target[0])
    rows = scenes.state_slice(n)
    pose = np.asarray(scenes.pose)
    room_xz = pose[rows, :2]
    seen = np.asarray(scenes.visible)[rows, target]
    path = pose[steps["state"], :2]
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.scatter(*np.unique(room_xz, axis=0).T, s=6, c="0.85", label="positions")
    ax.scatter(*np.unique(room_xz[seen], axis=0).T, s=14, c="tab:green",
               label=f"{CATEGORIES[target]} in view")
    ax.plot(*path.T, "-", c="tab:blue", lw=1.5, alpha=0.8, label="path")
    ax.scatter(*path[0], marker="s", s=70, c="tab:blue", label="start", zorder=3)
    ax.scatter(*path[-1], marker="*", s=160, zorder=3,
               c="tab:green" if outcome == "success" else "tab:red", label=f"end: {outcome}")
    if steps["deadlock"].any():
        ax.scatter(*path[steps["deadlock"]].T, marker="x", s=50, c="tab:red",
                   label="deadlock step")
    if "updated" in steps and steps["updated"].any():
        ax.scatter(*path[steps["updated"]].T, s=90, facecolors="none",
                   edgecolors="tab:orange", lw=1.5, label="TPN update")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_title(f"{got['name']}: {scenes.scene_names[n]}, target {CATEGORIES[target]}, "
                 f"{len(path)} steps", fontsize=9)
    ax.legend(fontsize=7, loc="best")
    return save_png(fig, Path(out) if out else Path(run_dir) / f"episode-{episode}.png")


def tpn_attention(run_dir: str | Path, episode: int = 0, split: str = "test", **kw) -> dict:
    """Where the TPN's memory read looked during one episode of a TPN run ->
    {"attention": (T, T) weights, row t = step t, column i = the memory slot of step i
    (its key r_i, its value r_{i+1} and p_i; only i < t can be read, k of them weigh),
    "updated": (T,) bool, the steps the test-time update took; "deadlock", "action"
    (T,); "name", "scene", "target", "outcome"}, T = the steps the episode took."""
    got = trace_run_episode(run_dir, episode, split, **kw)
    steps = got["steps"]
    if "tpn_attention" not in steps:
        raise UserError(f"{run_dir}: a training run; TPN attention exists only for a TPN "
                        "(stage 2) run (train --stage tpn)")
    return {"attention": steps["tpn_attention"], "updated": steps["updated"],
            "deadlock": steps["deadlock"], "action": steps["action"], "name": got["name"],
            "scene": got["scenes"].scene_names[int(got["episode"].scene[0])],
            "target": CATEGORIES[int(got["episode"].target[0])], "outcome": got["outcome"]}


def plot_tpn_attention(run_dir: str | Path, episode: int = 0, split: str = "test",
                       out: str | Path | None = None, step: int | None = None,
                       **kw) -> tuple[Path, dict]:
    """The paper's Fig. 3 (left) for one episode of a TPN run (tpn_attention): left, the
    read's weights, step t (rows) over earlier steps i (columns), darker = more weight,
    with the update and deadlock steps marked; right, the weights at one step (`step`,
    default the first update, else the last step) over the earlier steps, labelled with
    the action taken there -> (the PNG path, default RUN_DIR/tpn-attention-K.png, and
    the tpn_attention dict)."""
    plt = pyplot()
    att = tpn_attention(run_dir, episode, split, **kw)
    A, updated, T = att["attention"], att["updated"], len(att["updated"])
    if step is None:
        step = int(np.argmax(updated)) if updated.any() else T - 1
    if not 0 <= step < T:
        raise ValueError(f"--step {step}: the episode took steps 0...{T - 1}")
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.5), layout="constrained",
                                      gridspec_kw={"width_ratios": [1, 1.3]})
    im = left.imshow(A, cmap="Greys", vmin=0, vmax=max(float(A.max()), 1e-6),
                     origin="upper", interpolation="nearest")
    fig.colorbar(im, ax=left, fraction=0.046, label="attention weight p")
    for t in np.flatnonzero(att["deadlock"]):
        left.scatter(-1.2, t, marker="x", c="tab:red", s=25, clip_on=False)
    for t in np.flatnonzero(updated):
        left.scatter(-2.4, t, marker="o", facecolors="none", edgecolors="tab:orange",
                     s=30, clip_on=False)
    left.axhline(step, c="tab:blue", lw=0.8, alpha=0.6)
    left.set_xlim(-3, T - 0.5)
    left.set_xlabel("earlier step i (memory slot)")
    left.set_ylabel("step t   (x: deadlock, o: TPN update)")
    left.set_title(f"{att['name']}: {att['scene']}, target {att['target']}, "
                   f"{T} steps, {att['outcome']}", fontsize=9)
    past = np.arange(step)
    colours = ["tab:orange" if u else "tab:gray" for u in updated[:step]]
    right.bar(past, A[step, :step], color=colours)
    right.set_xticks(past)
    right.set_xticklabels([f"{i}:{ACTIONS[a]}" for i, a in zip(past, att["action"][:step])],
                          rotation=90, fontsize=6)
    right.set_ylabel("attention weight p")
    right.set_title(f"step {step}" + (" (TPN update)" if updated[step] else "") + (
        f": weights on steps 0...{step - 1}, action taken there (orange: updates)"
        if step else ": the first step, nothing to read yet"), fontsize=9)
    out = save_png(fig, Path(out) if out else Path(run_dir) / f"tpn-attention-{episode}.png")
    return out, dict(att, step=step)
