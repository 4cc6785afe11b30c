"""Memory estimates of the jitted training chunks, checked against available memory.

    check_memory(cfg, scenes)            # before a training run compiles (ValueError)
    check_tpn_memory(cfg, nav_cfg, scenes)   # before stage 2 compiles
    chunk_memory_bytes(cfg, scenes)      # -> {what: bytes} of one training chunk

The estimates count the large arrays a chunk holds at once: the runner state in and out
(parameters, Adam moments, each env's visited-state trail of episode_cap + 1 states), the
rollout's trajectory (num_envs x rollout_len steps), the loss's activations over those
steps and the scene arrays a run puts on the device (its train and val rooms only: the
SceneSet is flat and memory-mapped, so the test rooms are never loaded). They are
calibrated against XLA's own figure for the compiled chunk (memory_analysis;
docs/training.md: within a factor 1.2-1.7, above it) and are meant to catch
configurations that cannot fit at all (episode_cap 1e9 asks for most of a terabyte), not
to predict the peak to the byte: the check fails only when the estimate exceeds twice
the available memory, and prints a note when it exceeds it.
The process's fixed overhead (JAX, compiled code, ~1 GB on CPU) is not counted.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import jax
import numpy as np

from orgnav_jax.constants import FEATURE_GRID, NUM_ACTIONS, NUM_CATEGORIES, split_index
from orgnav_jax.models import build_model, init_params, tpn_net, vtnet

CELLS = FEATURE_GRID * FEATURE_GRID
C, A = NUM_CATEGORIES, NUM_ACTIONS
ERROR_FACTOR = 2.0     # fail when the estimate exceeds this many times the available memory

# bytes per env step that the rollout's Trajectory keeps (env.Observation: scene, state,
# det_box (C, 4), det_conf, target (C,), prev_action (A,) float32, deadlock; plus fresh,
# action, reward, done, value, expert_action, last_failed, failed, caused)
TRAJECTORY_STEP_BYTES = 8 + 4 * (4 * C + C + C + A) + 1 + 4 * 4 + 5
# copies of the (num_envs, episode_cap + 1) int32 trail a chunk holds at once: the runner's
# in and out, and the scan's working copy (XLA fuses the auto-reset's fresh trail)
TRAIL_COPIES = 3


def human(n: float) -> str:
    """Bytes in words: 512 B, 3.1 MB, 256 GB, 1.5 TB."""
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "B" or abs(n) >= 100 else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} PB"


def scene_bytes(scenes) -> int:
    """Bytes of a SceneSet's arrays (of a memory-mapped set: what loading it would take)."""
    return int(sum(getattr(getattr(scenes, f.name), "nbytes", 0)
                   for f in dataclasses.fields(scenes)))


def training_scene_bytes(scenes) -> int:
    """Bytes of the train and val views a training run holds (split views of a flat set
    hold only their own rooms' states)."""

    split = np.asarray(scenes.split)
    return sum(scene_bytes(scenes.split_view(s)) for s in ("train", "val")
               if (split == split_index(s)).any())


def param_count(cfg, scenes) -> int:
    """Parameters of the model cfg names for these scenes (shapes only: no arrays made)."""

    train = scenes.split_view("train")
    model = build_model(cfg, train)
    shapes = jax.eval_shape(lambda: init_params(model, jax.random.PRNGKey(0), train))
    return int(sum(x.size for x in jax.tree_util.tree_leaves(shapes)))


def _step_floats(cfg, scenes) -> int:
    """float32 activations per env step of the loss's replay (forward), all layers."""
    G, d, H = scenes.global_dim, scenes.appearance_dim, cfg.hidden
    gc, E, F = cfg.glob_channels, cfg.action_embed, cfg.fuse_channels
    inputs = CELLS * G + C * d + C * 6 + A
    encoder = C * CELLS + 2 * C * C + C * d          # category maps (+ ORG's relations)
    trunk = CELLS * (2 * gc + E + (gc + C + E) + F) + 4 * H
    recur = cfg.lstm_layers * 10 * H + 64 + 2 * A
    if cfg.model == "vtnet":        # the transformer's activations (models/vtnet.py)
        return inputs + vtnet.step_floats(cfg, C) + 4 * H + recur
    return inputs + encoder + trunk + recur


def chunk_memory_bytes(cfg, scenes, params: int | None = None) -> dict[str, int]:
    """Estimated bytes of one jitted training chunk, by what drives them:
    {"parameters": ..., "trail": ..., "trajectory": ..., "activations": ..., "scenes": ...}.
    `scenes`: the full SceneSet cfg trains on; `params`: the parameter count if known."""
    N, T = cfg.num_envs, cfg.rollout_len
    if cfg.savn:          # an update steps num_envs rows for savn_segments x savn_steps
        T = cfg.savn_segments * cfg.savn_steps                   # (training/savn.py)
    P = param_count(cfg, scenes) if params is None else params
    extra = {}
    if cfg.savn:
        # each row's low-rank fast weights: savn_inner_steps x savn_steps slots of each
        # LSTM layer's input, hidden state and 4 gates (input width taken as >= hidden),
        # kept for the meta-gradient: about three copies
        slots = cfg.savn_inner_steps * cfg.savn_steps
        extra["fast_weights"] = 4 * N * slots * 6 * cfg.hidden * cfg.lstm_layers * 3
    return {**extra,
        # params and Adam's two moments, in and out of the chunk (the gradient and update
        # are far smaller than the activations)
        "parameters": 4 * P * 6,
        "trail": 4 * N * (cfg.episode_cap + 1) * TRAIL_COPIES,
        "trajectory": N * T * TRAJECTORY_STEP_BYTES,
        # forward activations of the loss over N x T steps, kept for the backward pass
        # (XLA reuses their buffers for the gradients), plus one rollout step
        "activations": 4 * N * (T + 1) * _step_floats(cfg, scenes),
        "scenes": training_scene_bytes(scenes),
    }


def tpn_memory_bytes(cfg, nav_cfg, scenes, params: int | None = None) -> dict[str, int]:
    """Estimated bytes of one jitted stage-2 chunk, by what drives them: the base's
    episodes (num_envs x episode_cap steps: LSTM outputs, env trails), the TPN's activations
    over them and its (episode_cap x episode_cap) causal attention per episode (forward and
    backward), the base's parameters and the scenes."""
    N, T, H = cfg.num_envs, cfg.episode_cap, nav_cfg.hidden
    sig = 4 * cfg.signature_dim if cfg.deadlock == "cosine" else 0
    P = param_count(nav_cfg, scenes) if params is None else params
    return {
        "parameters": 4 * P * 2,
        "episodes": N * T * (4 * (H + A + 1) + 3 + sig)          # EpisodeBatch, detector
                    + 4 * N * _step_floats(nav_cfg, scenes),     # one step of the base
        "activations": 4 * 2 * N * T * tpn_net.step_floats(H, cfg.action_embed,
                                                          min(cfg.top_k, T)),
        "attention": 4 * N * T * T,      # the (T, T) scores of each episode (XLA fuses
                                         # the mask and the top-k into them)
        "trail": 4 * N * (T + 1) * TRAIL_COPIES,
        "scenes": training_scene_bytes(scenes),
    }


def available_memory() -> tuple[int | None, str]:
    """(bytes available to a run, where) on the default JAX device: a GPU's free memory
    (memory_stats: bytes_limit - bytes_in_use), else the host's MemAvailable (or physical
    memory). None if unknown."""
    try:
        dev = jax.local_devices()[0]
        stats = dev.memory_stats() if dev.platform != "cpu" else None
        if stats and stats.get("bytes_limit"):
            free = int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
            return free, f"free on the {dev.platform.upper()} ({dev.device_kind})"
    except Exception:       # no usable device statistics: fall back to the host
        pass
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "available (MemAvailable)"
    except OSError:
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "of physical memory"
    except (ValueError, OSError, AttributeError):
        return None, "unknown"


# what each part of an estimate scales with (config fields), for the error message
NAV_DRIVERS = {"parameters": "the widths hidden {hidden}, fuse_channels {fuse_channels}",
               "trail": "episode_cap {episode_cap} x num_envs {num_envs}",
               "trajectory": "num_envs {num_envs} x rollout_len {rollout_len}",
               "activations": "num_envs {num_envs} x rollout_len {rollout_len} x widths",
               "scenes": "the scene set",
               "fast_weights": "num_envs {num_envs} x savn_inner_steps {savn_inner_steps} "
                               "x savn_steps {savn_steps}"}
TPN_DRIVERS = {"parameters": "the base model's widths",
               "episodes": "num_envs {num_envs} x episode_cap {episode_cap}",
               "activations": "num_envs {num_envs} x episode_cap {episode_cap} x the "
                              "base's hidden width",
               "attention": "num_envs {num_envs} x episode_cap {episode_cap}^2",
               "trail": "num_envs {num_envs} x episode_cap {episode_cap}",
               "scenes": "the scene set"}


def _check(parts: dict[str, int], drivers: dict[str, str], cfg, what: str,
           available: int | None, where: str) -> int:
    total = sum(parts.values())
    if available is None:
        available, where = available_memory()
    if available is None or total <= available:
        return total
    big = sorted(parts, key=parts.get, reverse=True)
    drivers = "; ".join(f"{drivers[k].format(**dataclasses.asdict(cfg))}: "
                        f"~{human(parts[k])}" for k in big[:2] if parts[k] > total / 10)
    text = (f"{what} needs ~{human(total)} of memory per chunk ({drivers}); this machine "
            f"has {human(available)} {where}")
    if total > ERROR_FACTOR * available:
        raise ValueError(text + ": lower those fields")
    print(f"note: {text}; it may not fit", file=sys.stderr, flush=True)
    return total


def check_memory(cfg, scenes, available: int | None = None, where: str = "") -> int:
    """Raise ValueError if one training chunk of cfg clearly cannot fit in memory (the
    estimate exceeds ERROR_FACTOR x the available memory), naming the fields that drive
    it; print a note if it merely exceeds it. -> the estimate in bytes."""
    return _check(chunk_memory_bytes(cfg, scenes), NAV_DRIVERS, cfg, "training", available,
                  where)


def check_tpn_memory(cfg, nav_cfg, scenes, available: int | None = None,
                     where: str = "") -> int:
    """check_memory for a stage-2 (TPN) chunk of cfg on the base run nav_cfg."""
    return _check(tpn_memory_bytes(cfg, nav_cfg, scenes), TPN_DRIVERS, cfg, "TPN stage 2",
                  available, where)
