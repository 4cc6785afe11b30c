"""Write a preset's SceneSet to disk, streaming raw (decoded) features: preset 'large'.

A raw SceneSet stores the features themselves (float16, bases None), as the offline
importer stores the authors' data: global_feat (..., 7, 7, G) and appearance
(..., C, d) at the preset's widths. At paper widths that is ~72 KB per state, ~6 GB for
AI2-THOR's 40 val + test rooms, so such a set is never held in memory:

1. the rooms are built as usual with 16-bit codes and fixed projections (builder.build
   with raw=False: ~2 KB per state; room by room, with a progress bar);
2. storage.save writes every other field, and the two feature fields are decoded
   CHUNK states at a time with features.decode_global / decode_appearance (the same
   maths the model applies to codes, so the raw set holds float16 of exactly what the
   coded set decodes to) and appended to their .npy files as they are decoded.

Peak memory is the coded set plus one chunk, whatever the output's size; the decode
walks the features' leading (scene, state) axes in storage order, so it does not depend
on how the SceneSet lays out its states.

    from orgnav_jax import scenes
    scenes.build_to("large", 0, "data/large10", num_rooms=10, progress=True)
    s = scenes.load("data/large10", mmap=True)
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from orgnav_jax.safe_write import check_output_dir
from orgnav_jax.scenes.sceneset.assemble import STORE_DTYPE
from orgnav_jax.scenes.sceneset.features import decode_appearance, decode_global
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.sceneset.storage import is_scene_set, save
from orgnav_jax.scenes.synthetic.builder import build
from orgnav_jax.scenes.synthetic.presets import ScenePreset, get_preset

CHUNK = 512  # states decoded per jitted call (fixed shape: one compile per width)
BASES = ("global_basis", "appearance_basis", "appearance_proto")


@jax.jit
def _decode_global(basis, code):
    return decode_global(SimpleNamespace(global_basis=basis), code).astype(STORE_DTYPE)


@jax.jit
def _decode_appearance(basis, proto, code, conf):
    ns = SimpleNamespace(appearance_basis=basis, appearance_proto=proto)
    return decode_appearance(ns, code, conf.astype(jnp.float32)).astype(STORE_DTYPE)


def write_npy(path: str | os.PathLike, shape: tuple, dtype, chunks) -> tuple[tuple, np.dtype]:
    """Write a C-order .npy file of `shape` from an iterable of arrays whose
    concatenation along axis 0 is the array; only one chunk is in memory at a time.
    Returns (shape, dtype) for the SceneSet's meta.json."""
    dtype = np.dtype(dtype)
    want = math.prod(shape)
    written = 0
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {
            "descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
            "shape": tuple(int(n) for n in shape)})
        for chunk in chunks:
            chunk = np.ascontiguousarray(chunk, dtype)
            f.write(chunk.data)
            written += chunk.size
    if written != want:
        raise RuntimeError(f"{path}: wrote {written} values, expected {want} for shape {shape}")
    return tuple(shape), dtype


def _decoded_chunks(field: str, code: np.ndarray, conf: np.ndarray, bases: dict,
                    bar: tqdm):
    """Decode `code` (lead + (7, 7, Dg) or lead + (C, Da)) CHUNK states at a time."""
    tail = 3 if field == "global_feat" else 2
    rows = code.reshape((-1,) + code.shape[-tail:])       # views: (states, ...)
    conf = conf.reshape(-1, conf.shape[-1])
    n = rows.shape[0]
    for lo in range(0, n, CHUNK):
        hi = min(lo + CHUNK, n)
        idx = np.minimum(np.arange(lo, lo + CHUNK), n - 1)  # pad the last chunk
        if field == "global_feat":
            out = _decode_global(bases["global_basis"], jnp.asarray(rows[idx]))
        else:
            out = _decode_appearance(bases["appearance_basis"], bases["appearance_proto"],
                                     jnp.asarray(rows[idx]), jnp.asarray(conf[idx]))
        out = np.asarray(out)[:hi - lo]
        if not np.isfinite(out).all():
            row = lo + int(np.argmax(~np.isfinite(out).reshape(hi - lo, -1).all(1)))
            raise ValueError(f"{field}: a decoded feature of state row {row} overflows "
                             "float16; nothing was saved")
        bar.update(hi - lo)
        yield out


def _writer(field: str, coded: SceneSet, bases: dict, width: int, progress: bool):
    code = np.asarray(getattr(coded, field))
    conf = np.asarray(coded.det_conf)
    shape = code.shape[:-1] + (width,)

    def write(path: Path):
        states = math.prod(code.shape[:-3 if field == "global_feat" else -2])
        what = (f"global 7x7x{width}" if field == "global_feat"
                else f"appearance {code.shape[-2]}x{width}")
        with tqdm(total=states, desc=what, unit="state", disable=not progress) as bar:
            return write_npy(path, shape, STORE_DTYPE,
                             _decoded_chunks(field, code, conf, bases, bar))
    return write


def raw_view(coded: SceneSet) -> SceneSet:
    """`coded` as its raw set looks (bases None, features at the preset's widths), with
    zero-stride placeholder features: for shapes and summaries only, never for values."""
    G, d = coded.global_dim, coded.appearance_dim
    zero = np.zeros((), STORE_DTYPE)
    return coded.replace(
        global_feat=np.broadcast_to(zero, coded.global_feat.shape[:-1] + (G,)),
        appearance=np.broadcast_to(zero, coded.appearance.shape[:-1] + (d,)),
        **{k: None for k in BASES})


def build_raw_to(preset: str | ScenePreset, seed: int, out: str | os.PathLike, *,
                 progress: bool = False, **overrides) -> SceneSet:
    """Build `preset` (raw or not) with codes, then save it to `out` with its features
    decoded and streamed (module docstring). Returns raw_view of what was written."""
    check_output_dir(out, is_scene_set, "a SceneSet")  # before the build
    p = get_preset(preset, **overrides)
    coded = build(get_preset(p, raw=False), seed, progress=progress)
    coded = coded.replace(info=coded.info + (("features", "raw"),))
    bases = {k: jnp.asarray(getattr(coded, k)) for k in BASES}
    writers = {"global_feat": _writer("global_feat", coded, bases, coded.global_dim, progress),
               "appearance": _writer("appearance", coded, bases, coded.appearance_dim,
                                     progress)}
    # validate checks everything but the raw features (decoded chunk by chunk, checked
    # finite there): the coded set carries the same tables
    save(coded.replace(**{k: None for k in BASES}), out, writers=writers)
    return raw_view(coded)


def build_to(preset: str | ScenePreset, seed: int, out: str | os.PathLike, *,
             progress: bool = False, **overrides) -> Path:
    """Build a preset and save it to `out` (absent, empty or a SceneSet, replaced
    atomically); the features of raw presets ('large') are decoded and streamed chunk by
    chunk, so their size on disk never has to fit in memory. Returns the path; scenes.load(out)
    (mmap=True for raw sets) reads it."""
    p = get_preset(preset, **overrides)
    if p.raw:
        build_raw_to(p, seed, out, progress=progress)
    else:
        check_output_dir(out, is_scene_set, "a SceneSet")
        save(build(p, seed, progress=progress), out)
    return Path(out)
