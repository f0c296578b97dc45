"""Mapping: the multi-class semantic octree, submaps with exact re-anchoring, object landmarks.

- :class:`SemanticOctree` -- linear octree of clamped fixed-point semantic log-odds with
  vectorised scan insertion (:mod:`.raycast`), pruning, queries and files (:mod:`.octree_io`).
- :class:`SubmapMap` -- the map as ``clamp(prior + sum_s T_s . dh_s)``; ``move_submap`` is exact.
- :class:`ObjectMap` -- object landmarks from per-keyframe clusters and Hungarian association.
"""

from kimera_multi_py.mapping.detection import Detection, detect_objects
from kimera_multi_py.mapping.landmark import Landmark
from kimera_multi_py.mapping.objects import ObjectMap
from kimera_multi_py.mapping.observation import SCALE, ObservationModel
from kimera_multi_py.mapping.raycast import ScanCells, scan_cells
from kimera_multi_py.mapping.semantic_octree import Leaves, SemanticOctree
from kimera_multi_py.mapping.submaps import Submap, SubmapMap

__all__ = [
    "SCALE",
    "Detection",
    "Landmark",
    "Leaves",
    "ObjectMap",
    "ObservationModel",
    "ScanCells",
    "SemanticOctree",
    "Submap",
    "SubmapMap",
    "detect_objects",
    "scan_cells",
]
