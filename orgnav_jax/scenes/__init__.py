"""Scene data: the procedural benchmark, the flat (unpadded) SceneSet, expert tables.

The front door of three sub-packages, one job each (it imports the first two only):
scenes.sceneset, the data model every source produces and every consumer reads;
scenes.synthetic, the procedural generator; scenes.offline, the authors' offline format
(from orgnav_jax.scenes import offline). Beside them: summary.py (a set's summary) and
the command line (cli.py, __main__.py).

Notebook API::

    from orgnav_jax import scenes
    s = scenes.build("small", seed=0)      # SceneSet of numpy arrays
    scenes.save(s, "data/small")
    s = scenes.load("data/small", mmap=True)   # memory-mapped: nothing read yet
    train = s.split_view("train")          # only the train rooms' states (a view)
    dev = train.to_device()
    scenes.build_to("large", 0, "data/large10", num_rooms=10)   # raw, written to disk
"""

from orgnav_jax.scenes.sceneset.expert import expert_tables
from orgnav_jax.scenes.sceneset.features import (
    decode_appearance, decode_global, gather_features,
)
from orgnav_jax.scenes.sceneset.fields import NO_ACTION, UNREACHABLE
from orgnav_jax.scenes.sceneset.quantize import quantize_features
from orgnav_jax.scenes.sceneset.sceneset import SceneSet
from orgnav_jax.scenes.sceneset.storage import disk_size, load, save
from orgnav_jax.scenes.synthetic.builder import build
from orgnav_jax.scenes.synthetic.cache import device_split, load_or_build, load_scenes
from orgnav_jax.scenes.synthetic.layout import Room, generate_room, render_ascii
from orgnav_jax.scenes.synthetic.presets import SCENE_PRESETS, ScenePreset, get_preset
from orgnav_jax.scenes.synthetic.raw import build_to

__all__ = [
    "build", "build_to", "load", "save", "load_or_build", "load_scenes", "disk_size",
    "SceneSet", "ScenePreset",
    "SCENE_PRESETS", "get_preset", "expert_tables", "generate_room", "render_ascii", "Room",
    "decode_global", "decode_appearance", "gather_features", "UNREACHABLE", "NO_ACTION",
    "device_split", "quantize_features",
]
