"""Reuse a built benchmark across runs and within a process.

load_or_build: build once per (preset, seed, format version) into the cache directory,
then load; processes building the same set at once keep the first one saved. The
directory name carries the format version, so a new version rebuilds automatically and
code of an older version (another checkout sharing the cache) keeps reading its own copy.

load_scenes / device_split: within one process, the last SceneSet loaded (memory-mapped)
and its split views put on the device are kept, so that training, its val evaluation and
a test evaluation in the same process share one copy of each split.
"""

from __future__ import annotations

import os
from pathlib import Path

from orgnav_jax.constants import DEFAULT_SCENE_PRESET
from orgnav_jax.scenes.synthetic.builder import build
from orgnav_jax.scenes.sceneset.fields import FORMAT_VERSION
from orgnav_jax.scenes.synthetic.presets import get_preset
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.sceneset.storage import META_FILE, load, save


def default_cache_dir() -> Path:
    """$ORGNAV_CACHE, else ~/.cache/orgnav_jax."""
    return Path(os.environ.get("ORGNAV_CACHE", Path.home() / ".cache" / "orgnav_jax"))


def cache_path(preset: str, seed: int, cache_dir: str | os.PathLike | None = None) -> Path:
    """Where load_or_build keeps (preset, seed) in the current format version."""
    return Path(cache_dir or default_cache_dir()) / f"scenes-{preset}-seed{seed}-v{FORMAT_VERSION}"


def load_or_build(preset: str = DEFAULT_SCENE_PRESET, seed: int = 0,
                  cache_dir: str | os.PathLike | None = None, progress: bool = True,
                  mmap: bool = False) -> SceneSet:
    """The cached SceneSet for (preset, seed), built and saved on first use (memory-mapped
    when mmap=True and it was already on disk). Raw presets ('large', gigabytes) are never
    built here: build them with --out and load that."""
    if get_preset(preset).raw:
        raise ValueError(f"scene preset {preset!r} is real-size with raw features (~6 GB "
                         "for 40 rooms) and is not built into the cache: build it once with "
                         f"'python -m orgnav_jax.scenes build --preset {preset} --out DIR' "
                         "(--num-rooms N for fewer rooms), then use that directory "
                         "(--scenes DIR / scenes_dir=DIR)")
    path = cache_path(preset, seed, cache_dir)
    if (path / META_FILE).exists():
        return load(path, mmap=mmap)
    scenes = build(preset, seed, progress=progress)
    # never replaces a set another process saved meanwhile (it may be reading it)
    save(scenes, path, replace=False)
    return load(path, mmap=True) if mmap else scenes


_LOADED: dict = {}   # {"key": (what, identity of the files), "scenes": SceneSet, "splits": {}}


def _identity(path: Path) -> tuple:
    """Changes when the set at `path` is replaced (save renames a new directory in)."""
    try:
        st = (path / META_FILE).stat()
        return (str(path.resolve()), st.st_ino, st.st_mtime_ns)
    except OSError:
        return (str(path),)


def load_scenes(preset: str = DEFAULT_SCENE_PRESET, seed: int = 0,
                scenes_dir: str | None = None) -> SceneSet:
    """A saved SceneSet directory, else the cached preset, memory-mapped (split views of it
    read only their own rooms). The last one loaded is kept, so that loading a model and
    evaluating it in one process reads the set once; a set replaced on disk is reloaded."""
    if scenes_dir:
        key = ("dir", _identity(Path(scenes_dir)))
    else:
        key = ("preset", preset, seed, _identity(cache_path(preset, seed)))
    if _LOADED.get("key") != key:
        _LOADED.clear()
        scenes = (load(scenes_dir, mmap=True) if scenes_dir
                  else load_or_build(preset, seed, mmap=True))
        if not scenes_dir:   # a first build has just created the files
            key = ("preset", preset, seed, _identity(cache_path(preset, seed)))
        _LOADED.update(key=key, scenes=scenes, splits={})
    return _LOADED["scenes"]


def device_split(preset: str = DEFAULT_SCENE_PRESET, seed: int = 0, scenes_dir: str | None = None,
                 split: str = "train") -> SceneSet:
    """load_scenes(...).split_view(split).to_device(), kept with the loaded set: one
    device copy per split in a process (training, its val evaluation and a later
    evaluation share it)."""
    scenes = load_scenes(preset, seed, scenes_dir)
    splits = _LOADED["splits"]
    if split not in splits:
        splits[split] = scenes.split_view(split).to_device()
    return splits[split]


def clear_loaded() -> None:
    """Forget the set load_scenes keeps (and its device splits)."""
    _LOADED.clear()
