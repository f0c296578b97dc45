"""The 3D scene graph (DSG paper; Hydra): objects and agents, places, rooms and building (DESIGN §4.6).

- :func:`build_scene_graph` -- the layered graph of a semantic octree (:mod:`.places`, :mod:`.rooms`).
- :class:`SceneGraph` -- the layers as arrays; :mod:`.queries` answers questions on it.
- :func:`save_scene_graph` / :func:`load_scene_graph` -- ``dsg.json`` through Spark-DSG;
  :func:`to_networkx` -- a networkx view.
- :func:`true_rooms`, :func:`scene_graph_metrics` -- ground truth from the simulator and the scores.
- :func:`scene_graph_outputs` -- build, score and write, for a run.
- :func:`log_scene_graph` (in :mod:`.viz`) -- Rerun drawing with the layers at different heights.
"""

from kimera_multi_py.scene_graph.dsg_io import from_spark, load_scene_graph, save_scene_graph, to_networkx, to_spark
from kimera_multi_py.scene_graph.graph import SceneGraph, SceneGraphError, build_scene_graph, team_objects
from kimera_multi_py.scene_graph.metrics import scene_graph_metrics
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.scene_graph.queries import objects_in, path, room_of, where
from kimera_multi_py.scene_graph.truth import TrueRooms, true_rooms
from kimera_multi_py.scene_graph.workflow import graphs_agree, scene_graph_and_outputs, scene_graph_outputs

__all__ = [
    "SceneGraph",
    "SceneGraphError",
    "SceneGraphParams",
    "TrueRooms",
    "build_scene_graph",
    "from_spark",
    "graphs_agree",
    "load_scene_graph",
    "objects_in",
    "path",
    "room_of",
    "save_scene_graph",
    "scene_graph_and_outputs",
    "scene_graph_metrics",
    "scene_graph_outputs",
    "to_networkx",
    "team_objects",
    "to_spark",
    "true_rooms",
    "where",
]
