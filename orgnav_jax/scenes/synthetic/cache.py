"""Reuse a built benchmark across runs and within a process.

load_or_build: build once per (preset, seed, format version) into the cache directory,
then load; processes building the same set at once keep the first one saved. The
directory name carries the format version, so a new version rebuilds automatically and
code of an older version (another checkout sharing the cache) keeps reading its own copy.
Every load checks the cached set against the preset's whole definition (its info: the
preset, seed, rooms per type, room sizes, anchor probability, every perception knob, the
episode distances; the feature widths; the rooms, by FloorPlan number, type and split):
a set of another definition (an earlier one of the preset, another --perception, a slot
left by a test or an interrupted build) or a damaged one (meta.json gone, values out of
range) is rebuilt in place with a note; an entry holding files this program does not
write is refused, naming $ORGNAV_CACHE, before anything is built.

load_scenes / device_split: within one process, the last SceneSet loaded (memory-mapped)
and its split views put on the device are kept, so that training, its val evaluation and
a test evaluation in the same process share one copy of each split.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import numpy as np

from orgnav_jax.constants import DEFAULT_SCENE_PRESET, ROOM_TYPE_INDEX, SPLIT_INDEX
from orgnav_jax.errors import UserError
from orgnav_jax.scenes.synthetic.builder import build, preset_info
from orgnav_jax.scenes.synthetic.catalog import ANCHOR_PROBABILITY
from orgnav_jax.scenes.synthetic.perception import Perception
from orgnav_jax.scenes.sceneset.fields import FORMAT_VERSION
from orgnav_jax.scenes.synthetic.presets import (
    DEFAULT_EPISODE_DISTANCE, EPISODE_DISTANCE_KEY, ScenePreset, get_preset)
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.sceneset.storage import (
    META_FILE, foreign_files, load, remove_own_set, save)

CACHE_VARIABLE = "ORGNAV_CACHE"


def default_cache_dir() -> Path:
    """$ORGNAV_CACHE, else ~/.cache/orgnav_jax."""
    return Path(os.environ.get(CACHE_VARIABLE, Path.home() / ".cache" / "orgnav_jax"))


def cache_path(preset: str, seed: int, cache_dir: str | os.PathLike | None = None) -> Path:
    """Where load_or_build keeps (preset, seed) in the current format version."""
    return Path(cache_dir or default_cache_dir()) / f"scenes-{preset}-seed{seed}-v{FORMAT_VERSION}"


def load_or_build(preset: str = DEFAULT_SCENE_PRESET, seed: int = 0,
                  cache_dir: str | os.PathLike | None = None, progress: bool = True,
                  mmap: bool = False) -> SceneSet:
    """The cached SceneSet for (preset, seed), built and saved on first use (memory-mapped
    when mmap=True and it was already on disk). Raw presets ('large', gigabytes) are never
    built here: build them with --out and load that.

    A cached set is checked against the preset's definition on every load
    (definition_mismatch); one of another definition, or a damaged one, is rebuilt in
    place (a note on stderr says why); an entry holding files that are not a SceneSet's
    is refused (UserError naming the entry and $ORGNAV_CACHE) before anything is built."""
    if not isinstance(preset, str):
        raise ValueError(f"load_or_build caches the named presets; got a "
                         f"{type(preset).__name__}: build a changed preset with build() "
                         "and save it to a directory of your own")
    p = get_preset(preset)
    if p.raw:
        raise ValueError(f"scene preset {p.name!r} is real-size with raw features (~6 GB "
                         "for 40 rooms) and is not built into the cache: build it once with "
                         f"'python -m orgnav_jax.scenes build --preset {p.name} --out DIR' "
                         "(--num-rooms N for fewer rooms), then use that directory "
                         "(--scenes DIR / scenes_dir=DIR)")
    path = cache_path(p.name, seed, cache_dir)
    cached, why, damaged = _cached_entry(path, p, seed, mmap)
    if cached is not None:
        return cached
    if why is not None:
        print(f"note: the cached scene set {path} {why}: rebuilding it in place "
              f"(${CACHE_VARIABLE} is the cache directory)", file=sys.stderr, flush=True)
    seen = _identity(path)
    scenes = build(preset, seed, progress=progress)
    if damaged and _identity(path) == seen:   # (not rebuilt by another process meanwhile)
        # a damaged entry of ours (checked: only our files), moved aside, then removed
        aside = path.with_name(f".{path.name}.damaged-{os.getpid()}")
        try:
            path.rename(aside)
        except FileNotFoundError:
            pass
        else:
            remove_own_set(aside)
    # never replaces a set another process saved meanwhile (it may be reading it); a set
    # of another definition is replaced atomically (processes reading it keep their maps)
    save(scenes, path, replace=why is not None and not damaged)
    return load(path, mmap=True) if mmap else scenes


def _cached_entry(path: Path, preset: ScenePreset, seed: int,
                  mmap: bool) -> tuple[SceneSet | None, str | None, bool]:
    """The cache entry at `path` -> (its SceneSet when it is the set of (preset, seed),
    why it must be rebuilt otherwise (a phrase; None: there is none), whether it is
    damaged: its own files are removed before the rebuild is saved). UserError, naming
    $ORGNAV_CACHE, for an entry that is not the program's own."""
    if not path.exists() and not path.is_symlink():
        return None, None, False
    if path.is_symlink() or not path.is_dir():
        raise UserError(f"scene cache entry {path} is not a directory this program wrote "
                        f"(a file or a symbolic link): move it away, or set "
                        f"${CACHE_VARIABLE} to another directory")
    try:
        other = foreign_files(path)
    except OSError as err:
        raise UserError(f"scene cache entry {path} cannot be read ({err}); set "
                        f"${CACHE_VARIABLE} to another directory") from None
    if other:
        shown = ", ".join(other[:3]) + (f" and {len(other) - 3} more" if len(other) > 3 else "")
        raise UserError(f"scene cache entry {path} holds {shown}, which this program did "
                        f"not write: move them away, or set ${CACHE_VARIABLE} to another "
                        "directory")
    if not (path / META_FILE).is_file():
        return None, f"is damaged ({META_FILE} is missing)", True
    try:
        scenes = load(path, mmap=mmap)
    except (ValueError, OSError) as err:
        return None, f"is damaged ({err})", True
    differ = definition_mismatch(scenes, preset, seed)
    if differ:
        more = f" and {len(differ) - 3} more" if len(differ) > 3 else ""
        return None, (f"is not the set of preset {preset.name!r} seed {seed} as defined "
                      "now: " + "; ".join(differ[:3]) + more), False
    return scenes, None, False


def _default(key: str) -> str:
    """What a set built with the default of info `key` records: nothing (in words)."""
    name = key.removeprefix("perception.")
    if name != key and name in {f.name for f in dataclasses.fields(Perception)}:
        return f"{getattr(Perception(), name)!r} (the default, not recorded)"
    if key == "anchor_probability":
        return f"{ANCHOR_PROBABILITY!r} (the default, not recorded)"
    if key.startswith(EPISODE_DISTANCE_KEY):
        return f"{DEFAULT_EPISODE_DISTANCE!r} (the default, not recorded)"
    return "none (not recorded by this preset)"


def definition_mismatch(scenes: SceneSet, preset: ScenePreset, seed: int) -> list[str]:
    """What differs between `scenes` and the set build(preset, seed) makes, compared
    without building it: the info (preset, seed, rooms per type, room sizes and count,
    anchor probability, every perception knob, episode distances; builder.preset_info),
    the decoded feature widths and the rooms (FloorPlan number, room type, split, in
    order) ->
    ["perception.confusion 0.2, expected 0.15", ...], [] when none."""
    def plain(value):
        return tuple(value) if isinstance(value, list) else value
    got = {k: plain(v) for k, v in scenes.info}
    want = {k: plain(v) for k, v in preset_info(preset, seed)}
    out = []
    for key in list(want) + [k for k in got if k not in want]:
        if key not in got:
            out.append(f"{key} not recorded, expected {want[key]!r}")
        elif key not in want:
            out.append(f"{key} {got[key]!r}, expected {_default(key)}")
        elif got[key] != want[key]:
            out.append(f"{key} {got[key]!r}, expected {want[key]!r}")
    for name in ("global_dim", "appearance_dim"):
        if getattr(scenes, name) != getattr(preset, name):
            out.append(f"{name} {getattr(scenes, name)}, expected {getattr(preset, name)}")
    rooms = [(int(fp), ROOM_TYPE_INDEX[t], SPLIT_INDEX[s]) for fp, t, s in preset.floorplans()]
    held = list(zip(*(np.asarray(a).tolist() for a in (scenes.scene_id, scenes.room_type,
                                                        scenes.split))))
    if held != rooms:
        out.append(f"{len(held)} rooms, expected {len(rooms)}" if len(held) != len(rooms)
                   else "other rooms (FloorPlan numbers, types or splits) than the preset's")
    return out


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
