"""Save and load a SceneSet: a directory with `meta.json` and one `.npy` per field.

Format version 2 (sceneset.FORMAT_VERSION) stores the flat layout (sceneset.py:
per-state arrays (T, ...) over all rooms, state_offset and state_count per scene, int8
features with their scales when quantized). Version 1 sets (every room padded to the
largest, with a state_valid mask) still load: they are converted in memory on every load
(only the valid rows are kept), with a warning naming the command that converts them on
disk once: `python -m orgnav_jax.scenes convert OLD --out NEW`.

Saving is atomic (written beside the target, then renamed over it), so an interrupted
save never leaves a half-written set where a good one was. Saving replaces only an empty
directory or a SceneSet (is_scene_set: meta.json and our .npy files, nothing else):
anything else at the path is refused and left untouched. Loading checks the format
name, version, every field's presence, shape and dtype, then SceneSet.validate checks
the values (finite features, index ranges, expert tables), and names what is wrong.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np

from orgnav_jax.errors import field_error, is_int, is_number, read_field, read_object, read_str
from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.sceneset.fields import FORMAT_NAME, FORMAT_VERSION
from orgnav_jax.scenes.sceneset.flat import from_padded
from orgnav_jax.scenes.sceneset.sceneset import SceneSet

META_FILE = "meta.json"
_OPTIONAL = ("appearance_proto", "appearance_basis", "global_basis", "global_scale",
             "appearance_scale")
PADDED_VERSION = 1     # the padded layout: read and converted (flat.from_padded)
_PADDED_ONLY = ("state_valid",)              # fields of version 1 that version 2 lacks
_FLAT_ONLY = ("state_offset", "global_scale", "appearance_scale")


def _array_fields(version: int = FORMAT_VERSION) -> list[str]:
    names = [f.name for f in dataclasses.fields(SceneSet) if f.name != "info"]
    if version == PADDED_VERSION:
        names = [n for n in names if n not in _FLAT_ONLY] + list(_PADDED_ONLY)
    return names


def _own_files() -> set[str]:
    return ({META_FILE} | {f"{name}.npy" for name in _array_fields()}
            | {f"{name}.npy" for name in _PADDED_ONLY})


def convert_command(path, out: str = "NEW") -> str:
    """The command that rewrites an old-format set in the current format."""
    return f"python -m orgnav_jax.scenes convert {path} --out {out}"


def is_scene_set(path: str | os.PathLike) -> bool:
    """True if `path` is a SceneSet directory holding nothing but what `save` writes:
    meta.json naming our format, and only .npy files of SceneSet fields (so a set into
    which someone put their own files is not one: replacing it would delete them)."""
    path = Path(path)
    meta_path = path / META_FILE
    try:
        if not meta_path.is_file():
            return False
        meta = json.loads(meta_path.read_text())
        own = _own_files()
        entries = list(path.iterdir())
    except (OSError, ValueError, RecursionError):
        return False
    return (isinstance(meta, dict) and meta.get("format") == FORMAT_NAME
            and all(p.name in own and p.is_file() and not p.is_symlink() for p in entries))


def foreign_files(path: str | os.PathLike) -> list[str]:
    """The names in directory `path` that `save` does not write (not meta.json or a
    field's .npy, or not a plain file): [] for a SceneSet, a damaged one (say meta.json
    gone) and an empty directory."""
    own = _own_files()
    return sorted(p.name for p in Path(path).iterdir()
                  if p.name not in own or not p.is_file() or p.is_symlink())


def remove_own_set(path: str | os.PathLike) -> None:
    """Delete a (possibly damaged) SceneSet's own files in `path` and the directory if
    that empties it (remove_own_set of a path holding other files leaves them)."""
    _remove_own_set(Path(path))


def _remove_own_set(path: Path) -> None:
    """Delete the files `save` writes in `path`, then the directory if that empties it
    (anything else found there is left, with a warning)."""
    own = _own_files()
    for p in path.iterdir():
        if p.name in own and (p.is_file() or p.is_symlink()):
            p.unlink()
    try:
        path.rmdir()
    except OSError:
        warnings.warn(f"{path}: left in place (it holds files that are not part of a "
                      "SceneSet)", stacklevel=3)


def save(scenes: SceneSet, path: str | os.PathLike, validate: bool = True, *,
         writers: dict | None = None, replace: bool = True) -> Path:
    """Write `scenes` to directory `path`, replacing an existing SceneSet there
    atomically. Returns the path. replace=False keeps a SceneSet that is at `path` when
    the new one is ready (another process saved the same set meanwhile: a cache) and
    drops the new one.

    Refuses (FileExistsError, nothing written) a path that is a file or a non-empty
    directory that is not a SceneSet (is_scene_set). validate=True first checks the set
    (SceneSet.validate), so an invalid set is never written.

    writers: {field: write(file) -> (shape, dtype)} for fields too large to hold in
    memory: each writes its own .npy file (e.g. streamed chunk by chunk, see
    synthetic/raw.py) in place of the value in `scenes`, which validate checks instead.
    """
    path = Path(path)
    if path.is_symlink():
        path = path.resolve()  # replace the directory it points to; the link stays
    check_output_dir(path, is_scene_set, "a SceneSet", option="output")
    if validate:
        scenes.validate(f"SceneSet to save to {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    old = None
    try:
        fields = {}
        for name in _array_fields():
            if writers and name in writers:
                shape, dtype = writers[name](tmp / f"{name}.npy")
                fields[name] = {"shape": list(shape), "dtype": str(np.dtype(dtype))}
                continue
            value = getattr(scenes, name)
            if value is None:
                continue
            arr = np.asarray(value)
            np.save(tmp / f"{name}.npy", arr, allow_pickle=False)
            fields[name] = {"shape": list(arr.shape), "dtype": str(arr.dtype)}
        info = dict(scenes.info)
        meta = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
                "info": {k: list(v) if isinstance(v, tuple) else v for k, v in info.items()},
                "fields": fields}
        (tmp / META_FILE).write_text(json.dumps(meta, indent=1))
        # checked again: the path may have changed while the arrays were written
        check_output_dir(path, is_scene_set, "a SceneSet", option="output")
        if not replace:
            try:                          # atomic: fails if a set is there by now
                tmp.rename(path)
            except OSError:
                if not is_scene_set(path):
                    raise
                shutil.rmtree(tmp, ignore_errors=True)
            return path
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            k = 0
            while old.exists() or old.is_symlink():  # never delete what we did not write
                k += 1
                old = path.with_name(f".{path.name}.old{k}")
            path.rename(old)
        tmp.rename(path)
        if old is not None:
            _remove_own_set(old)
    except BaseException:
        if old is not None and old.exists() and not path.exists():
            old.rename(path)  # interrupted between the two renames: put the old set back
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


def load(path: str | os.PathLike, mmap: bool = False) -> SceneSet:
    """Read a SceneSet saved by `save` (numpy arrays; memory-mapped if mmap=True: then
    nothing is read into memory beyond what validation streams through, and split views
    of the set are views of the maps).

    A version-1 (padded) set is converted in memory (a warning names the `convert`
    command). Raises FileNotFoundError / ValueError naming the file or field when `path`
    is not a SceneSet directory, is from an unknown format version, or is truncated.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no SceneSet at {path}: the path does not exist")
    if path.is_file():
        if path.name == META_FILE:
            path = path.parent
        else:
            raise ValueError(f"{path} is a file, expected a SceneSet directory holding "
                             f"{META_FILE} and one .npy per field (made by scenes.save or "
                             "'python -m orgnav_jax.scenes build')")
    meta_path = path / META_FILE
    if not meta_path.exists():
        raise ValueError(f"{path} is not a SceneSet directory: {META_FILE} is missing")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{meta_path} is not valid JSON ({e}): not a SceneSet") from None
    except RecursionError:
        raise ValueError(f"{meta_path}: JSON nested too deeply: not a SceneSet") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise ValueError(f"{meta_path}: format is {got!r}, expected {FORMAT_NAME!r}")
    version = meta.get("version")
    if not is_int(version) or version not in (FORMAT_VERSION, PADDED_VERSION):
        raise ValueError(f"{meta_path}: format version {version!r}, this orgnav_jax reads "
                         f"versions {PADDED_VERSION} and {FORMAT_VERSION}; rebuild the scenes")
    fields, info = read_meta_fields(meta, meta_path)
    arrays = {}
    for name in _array_fields(version):
        if name not in fields:
            if name in _OPTIONAL:
                continue
            raise ValueError(f"{meta_path}: field {name!r} is missing")
        file = path / f"{name}.npy"
        if not file.exists():
            raise ValueError(f"{path}: file {file.name} for field {name!r} is missing")
        try:
            arr = np.load(file, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"{file}: cannot read field {name!r} ({e}); the file is "
                             "truncated or not a .npy array") from None
        want = fields[name]
        if list(arr.shape) != want["shape"] or str(arr.dtype) != want["dtype"]:
            raise ValueError(f"{file}: field {name!r} has shape {arr.shape} dtype {arr.dtype}, "
                             f"meta.json says {tuple(want['shape'])} {want['dtype']}")
        arrays[name] = arr
    if version == PADDED_VERSION:
        scenes = _from_padded_file(path, arrays, info)
    else:
        scenes = SceneSet(**arrays, info=info)
    scenes.validate(str(path))
    return scenes


def _plain(value) -> bool:
    """A JSON scalar (string, number, boolean, null): what an info entry may hold, alone
    or in a list."""
    return value is None or isinstance(value, str) or is_number(value) or \
        isinstance(value, bool)


def read_meta_fields(meta: dict, meta_path) -> tuple[dict, tuple]:
    """The typed part of meta.json: "fields" {field: {"shape": [int >= 0, ...], "dtype":
    str}} and "info" {key: scalar or list of scalars} -> (fields, info tuple). ValueError
    naming meta.json and the field otherwise (the format and version: load)."""
    fields = read_object(meta.get("fields", {}), f"{meta_path}: field 'fields'",
                         "an object {field: {'shape': [...], 'dtype': ...}}")
    for name, want in fields.items():
        where = f"{meta_path}: fields[{name!r}]"
        read_object(want, where, "an object {'shape': [int, ...], 'dtype': str}")
        shape = read_field(want, "shape", where)
        if not isinstance(shape, list) or not all(is_int(n) and 0 <= n <= 2 ** 62
                                                  for n in shape):
            raise field_error(where, "shape", "a list of integers >= 0", shape)
        read_str(want, "dtype", where)
    info = read_object(meta.get("info", {}), f"{meta_path}: field 'info'",
                       "an object {key: value}")
    for key, value in info.items():
        if not (_plain(value) or isinstance(value, list) and all(map(_plain, value))):
            raise field_error(f"{meta_path}: info", key,
                              "a string, number, boolean, null or a list of those", value)
    ids, names = info.get("room_name_ids", []), info.get("room_names", [])
    if not (isinstance(ids, list) and all(map(is_int, ids))):
        raise field_error(f"{meta_path}: info", "room_name_ids", "a list of integers", ids)
    if not (isinstance(names, list) and all(isinstance(n, str) for n in names)) \
            or len(names) != len(ids):
        raise field_error(f"{meta_path}: info", "room_names",
                          f"a list of {len(ids)} strings (one per room_name_ids)", names)
    return fields, tuple((k, tuple(v) if isinstance(v, list) else v) for k, v in info.items())


def _from_padded_file(path: Path, arrays: dict, info: tuple) -> SceneSet:
    """A version-1 (padded) set, converted in memory (flat.from_padded), with a warning."""
    valid = arrays.get("state_valid")
    if valid is None or valid.ndim != 2 or valid.dtype != bool:
        raise ValueError(f"{path}: format version {PADDED_VERSION} needs field 'state_valid' "
                         "(N, S) bool")
    for name in ("next_state", "pose", "visible", "dist", "expert_action", "det_box",
                 "det_conf", "appearance", "global_feat"):
        if tuple(arrays[name].shape[:2]) != valid.shape:
            raise ValueError(f"{path}: field {name!r} has shape {arrays[name].shape}, "
                             f"expected (N, S, ...) = {valid.shape} + ... in format version "
                             f"{PADDED_VERSION}")
    counts = valid.sum(1)
    if not (valid == (np.arange(valid.shape[1])[None] < counts[:, None])).all():
        raise ValueError(f"{path}: field 'state_valid' must be True exactly on the first "
                         "states of each scene (format version 1)")
    warnings.warn(f"{path}: a SceneSet of format version {PADDED_VERSION} (every room padded "
                  "to the largest); converted in memory on each load. Convert it on disk once:"
                  f" {convert_command(path)}", stacklevel=3)
    info = tuple((k, FORMAT_VERSION if k == "version" else v) for k, v in info)
    return from_padded(arrays, info)


def disk_size(path: str | os.PathLike) -> int:
    """Bytes used by a saved SceneSet directory."""
    return sum(f.stat().st_size for f in Path(path).iterdir() if f.is_file())
