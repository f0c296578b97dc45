"""The 3D scene graph (DSG paper; Hydra): objects and agents, places, rooms and building
(docs/algorithms/scene_graph.md).

- :func:`build_scene_graph` -- the layered graph of a semantic octree (:mod:`.places`, :mod:`.rooms`).
- :class:`SceneGraph` -- the layers as arrays; :mod:`.queries` answers questions on it.
- :func:`save_scene_graph` / :func:`load_scene_graph` -- ``dsg.json`` through Spark-DSG;
  :func:`to_networkx` -- a networkx view.
- Scoring against the simulator's truth, and writing a run's graph, live in
  :mod:`kimera_multi_py.eval.scene_graph`.
- :func:`log_scene_graph` (in :mod:`.viz`) -- Rerun drawing with the layers at different heights.
"""

from kimera_multi_py.scene_graph.dsg_io import from_spark, load_scene_graph, save_scene_graph, to_networkx, to_spark
from kimera_multi_py.scene_graph.graph import SceneGraph, SceneGraphError, build_scene_graph, team_objects
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.scene_graph.queries import objects_in, path, room_of, where

__all__ = [
    "SceneGraph",
    "SceneGraphError",
    "SceneGraphParams",
    "build_scene_graph",
    "from_spark",
    "load_scene_graph",
    "objects_in",
    "path",
    "room_of",
    "save_scene_graph",
    "to_networkx",
    "team_objects",
    "to_spark",
    "where",
]
