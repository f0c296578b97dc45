"""Rerun drawing of a scene graph with its layers stacked at different heights, as Hydra draws them.

Objects and agents stay where they are; places are lifted by ``layer_gap``, rooms by twice and
the building by three times that. Lines join each node to its parent, places to each other and
rooms to each other. Places and rooms are coloured by room, objects by class.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.semantics import CLASS_COLORS, CLASS_NAMES
from kimera_multi_py.scene_graph.dsg_io import room_color
from kimera_multi_py.scene_graph.graph import SceneGraph

_GREY = np.array([150, 150, 150], dtype=np.uint8)


def _strips(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack([a, b], axis=1).reshape(-1, 2, 3)


def log_scene_graph(g: SceneGraph, rec: Any, T_world_map: np.ndarray | None = None, entity: str = "scene_graph",
                    layer_gap: float = 3.0) -> None:
    """Log ``g`` (placed in the world by ``T_world_map``) into the Rerun recording stream ``rec``."""
    import rerun as rr

    T = np.eye(4) if T_world_map is None else np.asarray(T_world_map, dtype=np.float64)
    up = np.array([0.0, 0.0, layer_gap])
    place_c = np.array([room_color(int(r)) if r >= 0 else _GREY for r in g.place_room], dtype=np.uint8).reshape(-1, 3)
    room_c = np.array([room_color(r) for r in range(g.num_rooms)], dtype=np.uint8).reshape(-1, 3)
    P = transform_points(T, g.place_pos).reshape(-1, 3) + up
    R = transform_points(T, g.room_pos).reshape(-1, 3) + 2 * up
    B = transform_points(T, g.building_pos[None])[0] + 3 * up
    O = transform_points(T, g.object_pos).reshape(-1, 3)
    A = transform_points(T, g.agent_pose[:, :3, 3]).reshape(-1, 3)
    rec.log(f"{entity}/places", rr.Points3D(P, colors=place_c, radii=0.08), static=True)
    rec.log(f"{entity}/place_edges", rr.LineStrips3D(_strips(P[g.place_edges[:, 0]], P[g.place_edges[:, 1]]),
                                                     colors=[[120, 120, 120]], radii=0.01), static=True)
    rec.log(f"{entity}/rooms", rr.Points3D(R, colors=room_c, radii=0.3,
                                           labels=[f"R({r})" for r in range(g.num_rooms)]), static=True)
    rec.log(f"{entity}/room_edges", rr.LineStrips3D(_strips(R[g.room_edges[:, 0]], R[g.room_edges[:, 1]]),
                                                    colors=[[30, 30, 30]], radii=0.04), static=True)
    rec.log(f"{entity}/building", rr.Points3D(B[None], colors=[[0, 0, 0]], radii=0.5, labels=["building"]),
            static=True)
    m = g.place_room >= 0
    rec.log(f"{entity}/place_to_room", rr.LineStrips3D(_strips(P[m], R[g.place_room[m]]), colors=place_c[m],
                                                       radii=0.005), static=True)
    rec.log(f"{entity}/room_to_building", rr.LineStrips3D(_strips(R, np.repeat(B[None], len(R), 0)),
                                                          colors=room_c, radii=0.02), static=True)
    if len(O):
        oc = CLASS_COLORS[g.object_class]
        rec.log(f"{entity}/objects", rr.Points3D(O, colors=oc, radii=0.1,
                                                 labels=[CLASS_NAMES[c] for c in g.object_class]), static=True)
        k = g.object_place >= 0
        rec.log(f"{entity}/object_to_place", rr.LineStrips3D(_strips(O[k], P[g.object_place[k]]), colors=oc[k],
                                                             radii=0.01), static=True)
    if len(A):
        k = g.agent_place >= 0
        rec.log(f"{entity}/agents", rr.Points3D(A, colors=[[40, 40, 200]], radii=0.05), static=True)
        rec.log(f"{entity}/agent_to_place", rr.LineStrips3D(_strips(A[k], P[g.agent_place[k]]),
                                                            colors=[[40, 40, 200]], radii=0.003), static=True)
