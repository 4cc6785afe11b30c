"""The SceneSet's field names by axis, its sentinels and its on-disk format name.

Plain constants, imported by the SceneSet (sceneset.py), its checks (checks.py) and every
module that reads the tables, so that none of them needs another's code.
"""

from __future__ import annotations

FORMAT_NAME = "orgnav_jax.sceneset"   # meta.json "format" and SceneSet.info of saved sets
FORMAT_VERSION = 2  # 2: flat (unpadded) state axis, state_offset, optional int8 scales;
                    # 1: every room padded to the largest (read by storage.load, converted)
FORMAT_INFO = (("format", FORMAT_NAME), ("version", FORMAT_VERSION))  # first info pairs
UNREACHABLE = 32767   # dist sentinel (int16 max): no state seeing the category is reachable
NO_ACTION = -1        # expert_action sentinel for unreachable targets
PER_STATE_FIELDS = ("next_state", "pose", "visible", "dist", "expert_action", "det_box",
                    "det_conf", "appearance", "global_feat")
PER_SCENE_FIELDS = ("present", "targets", "state_offset", "state_count", "room_type",
                    "scene_id", "split")
SHARED_FIELDS = ("appearance_proto", "appearance_basis", "global_basis", "global_scale",
                 "appearance_scale", "info")
SCALE_OF = {"global_feat": "global_scale", "appearance": "appearance_scale"}
