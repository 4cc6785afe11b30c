"""Reuse a built benchmark across runs: build once per (preset, seed), then load."""

from __future__ import annotations

import functools
import os
from pathlib import Path

from orgnav_jax.scenes.builder import build
from orgnav_jax.scenes.presets import get_preset
from orgnav_jax.scenes.sceneset import SceneSet
from orgnav_jax.scenes.storage import META_FILE, load, save


def default_cache_dir() -> Path:
    """$ORGNAV_CACHE, else ~/.cache/orgnav_jax."""
    return Path(os.environ.get("ORGNAV_CACHE", Path.home() / ".cache" / "orgnav_jax"))


def load_or_build(preset: str = "small", seed: int = 0, cache_dir: str | os.PathLike | None = None,
                  progress: bool = True) -> SceneSet:
    """The cached SceneSet for (preset, seed), built and saved on first use. Raw presets
    ('large', gigabytes) are never built here: build them with --out and load that."""
    if get_preset(preset).raw:
        raise ValueError(f"scene preset {preset!r} is real-size with raw features (~6 GB "
                         "for 40 rooms) and is not built into the cache: build it once with "
                         f"'python -m orgnav_jax.scenes build --preset {preset} --out DIR' "
                         "(--num-rooms N for fewer rooms), then use that directory "
                         "(--scenes DIR / scenes_dir=DIR)")
    path = Path(cache_dir or default_cache_dir()) / f"scenes-{preset}-seed{seed}"
    if (path / META_FILE).exists():
        return load(path)
    scenes = build(preset, seed, progress=progress)
    save(scenes, path)
    return scenes


@functools.lru_cache(maxsize=1)
def load_scenes(preset: str = "small", seed: int = 0, scenes_dir: str | None = None) -> SceneSet:
    """A saved SceneSet directory, else the cached preset; the last one is kept in memory,
    so that loading a model and evaluating it in one process reads the set once."""
    return load(scenes_dir) if scenes_dir else load_or_build(preset, seed)
