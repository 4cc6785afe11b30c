"""Scene data: the procedural benchmark, the flat (unpadded) SceneSet, expert tables.

Notebook API::

    from orgnav_jax import scenes
    s = scenes.build("small", seed=0)      # SceneSet of numpy arrays
    scenes.save(s, "data/small")
    s = scenes.load("data/small", mmap=True)   # memory-mapped: nothing read yet
    train = s.split_view("train")          # only the train rooms' states (a view)
    dev = train.to_device()
    scenes.build_to("large", 0, "data/large10", num_rooms=10)   # raw, written to disk
"""

from orgnav_jax.scenes.builder import build
from orgnav_jax.scenes.expert import expert_tables
from orgnav_jax.scenes.features import decode_appearance, decode_global, gather_features
from orgnav_jax.scenes.layout import Room, generate_room, render_ascii
from orgnav_jax.scenes.presets import SCENE_PRESETS, ScenePreset, get_preset
from orgnav_jax.scenes.sceneset import NO_ACTION, UNREACHABLE, SceneSet
from orgnav_jax.scenes.storage import disk_size, load, save
from orgnav_jax.scenes.cache import device_split, load_or_build, load_scenes
from orgnav_jax.scenes.quantize import quantize_features
from orgnav_jax.scenes.raw import build_to

__all__ = [
    "build", "build_to", "load", "save", "load_or_build", "load_scenes", "disk_size",
    "SceneSet", "ScenePreset",
    "SCENE_PRESETS", "get_preset", "expert_tables", "generate_room", "render_ascii", "Room",
    "decode_global", "decode_appearance", "gather_features", "UNREACHABLE", "NO_ACTION",
    "device_split", "quantize_features",
]
