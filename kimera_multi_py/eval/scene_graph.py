"""Workflow: build a scene graph from a run's map, score it against the simulator, write ``dsg.json``."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.eval.scene_graph_metrics import scene_graph_metrics
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.scene_graph.dsg_io import save_scene_graph
from kimera_multi_py.scene_graph.graph import SceneGraph, build_scene_graph
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.world import World


def scene_graph_outputs(octree: SemanticOctree, T_world_map: np.ndarray | None, landmarks: Iterable[Any],
                        trajectories: Mapping[int, tuple[np.ndarray, np.ndarray]] | None,
                        world_or_scenario: World | ScenarioConfig | None, out_path: str | Path | None,
                        params: SceneGraphParams | None = None) -> dict[str, Any]:
    """Build the graph of one map (in the map's frame), write it to ``out_path`` (``dsg.json``; None
    writes nothing) and return the ``results.json["scene_graph"]`` figures, scored in the world
    through ``T_world_map`` (without a world: only ``rooms_found``, ``nodes_per_layer`` and ``build_s``).
    :func:`scene_graph_and_outputs` also returns the graph."""
    return scene_graph_and_outputs(octree, T_world_map, landmarks, trajectories, world_or_scenario, out_path,
                                   params)[1]


def scene_graph_and_outputs(octree: SemanticOctree, T_world_map: np.ndarray | None, landmarks: Iterable[Any],
                            trajectories: Mapping[int, tuple[np.ndarray, np.ndarray]] | None,
                            world_or_scenario: World | ScenarioConfig | None, out_path: str | Path | None,
                            params: SceneGraphParams | None = None,
                            people: Iterable[Any] = ()) -> tuple[SceneGraph, dict[str, Any]]:
    """:func:`scene_graph_outputs`, also returning the graph (for agreement checks and Rerun);
    ``people`` are the map frame's people (docs/algorithms/people.md)."""
    T = np.eye(4) if T_world_map is None else np.asarray(T_world_map, dtype=np.float64)
    g = build_scene_graph(octree, landmarks, trajectories, params, people)
    g.metadata["T_world_map"] = T.tolist()
    if out_path is not None:
        save_scene_graph(g, out_path)
    if world_or_scenario is None:
        return g, {"rooms_found": g.num_rooms, "nodes_per_layer": g.nodes_per_layer(),
                   "build_s": float(g.metadata["build_s"])}
    return g, scene_graph_metrics(g, world_or_scenario, T)


def graphs_agree(graphs: Sequence[SceneGraph]) -> dict[str, bool]:
    """Whether graphs built from the same (consensus) map agree: the same places, the same room of
    every place, and the same room for every object id they share."""
    if len(graphs) < 2:
        return {"places": True, "rooms": True, "object_rooms": True}
    a = graphs[0]
    places = all(np.array_equal(a.place_ids, g.place_ids) for g in graphs[1:])
    rooms = places and all(np.array_equal(a.place_room, g.place_room) for g in graphs[1:])
    ok = True
    ra = dict(zip(a.object_ids.tolist(), a.object_room().tolist(), strict=True))
    for g in graphs[1:]:
        rg = dict(zip(g.object_ids.tolist(), g.object_room().tolist(), strict=True))
        ok &= all(ra[k] == rg[k] for k in set(ra) & set(rg))
    return {"places": bool(places), "rooms": bool(rooms), "object_rooms": bool(ok)}
