"""The authors' offline AI2-THOR data format (see docs/offline.md):
import FloorPlanN folders into a SceneSet and export any SceneSet to them; their
evaluation episodes, JSON or pickle, are read and written by
orgnav_jax.scenes.offline.episodes (as EpisodeSets, the data model's:
scenes/sceneset/episodes.py). A scene source beside scenes/synthetic: it imports only
the data model, and nothing below it imports it.

    from orgnav_jax import scenes
    from orgnav_jax.scenes import offline
    s, report = offline.import_offline("Data/AI2thor_offline_data")
    scenes.save(s, "data/thor")                      # or offline.import_to(dir, out)
    offline.export_offline(scenes.build("tiny", 0), "out/offline")

CLI: python -m orgnav_jax.scenes import --offline-dir DIR --out OUT
     python -m orgnav_jax.scenes export --preset tiny --out DIR
"""

from orgnav_jax.scenes.offline.exporter import export_offline, object_ids
from orgnav_jax.scenes.offline.features_io import detection_rows
from orgnav_jax.scenes.offline.importer import (
    format_report, import_offline, import_to, scene_folders,
)
from orgnav_jax.scenes.offline.reader import read_scene
from orgnav_jax.scenes.offline.validate import OfflineFormatError

__all__ = [
    "import_offline", "import_to", "export_offline", "OfflineFormatError", "read_scene",
    "scene_folders", "format_report", "object_ids", "detection_rows",
]
