"""File names of one scene folder in the authors' offline format (see
docs/offline.md): `<dir>/FloorPlanN/<file>`."""

from __future__ import annotations

GRAPH_FILE = "graph.json"                      # networkx node_link_data of the state graph
GRID_FILE = "grid.json"                        # reachable points [{"x", "y", "z"}]
VISIBLE_FILES = ("visible_object_map_1.5.json", "visible_object_map.json")  # first found
OPTIMAL_FILE = "optimal_action.json"           # optional: key -> {type: action index}
RESNET_FILE = "resnet18_featuremap.hdf5"       # key -> (1, G, 7, 7)
# Detection hdf5 names seen in the release and its descendants, tried in this order
# unless a name is given: key -> (rows, d + 5) = appearance d, box x1 y1 x2 y2, confidence.
DETECTION_FILES = ("fasterrcnn_features_22cls.hdf5", "det_feature_categories.hdf5",
                   "det_feature_22_categories.hdf5", "det_feature_60_categories.hdf5",
                   "detr_features_22cls.hdf5")
EXPORT_DETECTION_FILE = DETECTION_FILES[0]
GRID_Y = 0.9009995  # the agent's y in the authors' rooms; written into exported grid.json
