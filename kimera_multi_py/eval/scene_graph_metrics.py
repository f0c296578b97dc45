"""Scene-graph quality against the simulator's ground truth (docs/algorithms/scene_graph.md, Hydra's ``room_metrics``).

Rooms
    A true room's voxels are the ground-truth free voxels inside its box (Hydra counts the
    observed free TSDF voxels in each box). An estimated room's voxels are the union of its places'
    free-space spheres (radius = clearance), restricted to voxels inside some true room.
    ``room_recall`` = Σ_true max_est overlap / Σ_true size and ``room_precision`` = Σ_est max_true
    overlap / Σ_est size (the pooled form); ``room_recall_mean`` / ``room_precision_mean`` are
    the per-room means that Hydra's ``eval_rooms`` prints.
Objects
    Each estimated room stands for the true room it overlaps most; an object is right when that
    room is the true room holding the object's centroid (objects outside every true room are not
    scored).
Places
    ``place_coverage``: the fraction of free floor cells (free ground-truth cells in the first layer
    above the floor, inside the true rooms) within ``coverage_radius`` (horizontally) of a place.
Room kinds
    ``room_kinds.accuracy``: the share of estimated rooms whose kind (:mod:`~kimera_multi_py.scene_graph.kinds`)
    is the kind the kind table gives the layout of the true room they stand for.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.eval.scene_graph_truth import TrueRooms, as_world, true_rooms
from kimera_multi_py.scene_graph.graph import SceneGraph
from kimera_multi_py.scene_graph.kinds import load_kind_table
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.world import World


def room_overlap(g: SceneGraph, truth: TrueRooms, voxels: np.ndarray, T_world_map: np.ndarray,
                 resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(overlap (true, est), true sizes, est sizes)`` in voxels; ``voxels`` are free world points."""
    t_of = truth.containing(voxels)
    V, t_of = voxels[t_of >= 0], t_of[t_of >= 0]
    nt, ne = len(truth), g.num_rooms
    true_size = np.bincount(t_of, minlength=nt).astype(np.float64)
    m = g.place_room >= 0
    if ne == 0 or not m.any() or len(V) == 0:
        return np.zeros((nt, ne)), true_size, np.zeros(ne)
    P = transform_points(T_world_map, g.place_pos[m])
    radius, room = g.place_clearance[m], g.place_room[m]
    pairs = cKDTree(P).sparse_distance_matrix(cKDTree(V), float(radius.max()) + 1e-9, output_type="ndarray")
    inside = pairs["v"] <= radius[pairs["i"]] + 1e-9
    key = np.unique(pairs["j"][inside].astype(np.int64) * ne + room[pairs["i"][inside]])
    vox, est = key // ne, key % ne
    est_size = np.bincount(est, minlength=ne).astype(np.float64)
    overlap = np.bincount(t_of[vox] * ne + est, minlength=nt * ne).reshape(nt, ne).astype(np.float64)
    return overlap, true_size, est_size


def room_kind_scores(g: SceneGraph, world: World, truth: TrueRooms, match: np.ndarray) -> dict[str, Any]:
    """Each estimated room's kind against the layout of the true room it stands for (rooms whose true
    room has no layout the kind table knows are not scored)."""
    table = load_kind_table()
    layout = {s.name: s.layout for s in world.cfg.spaces}
    rooms, right = {}, []
    for e, t in enumerate(match.tolist()):
        kind = g.room_kind[e] if e < len(g.room_kind) else None
        spaces = truth.names[t].split("+") if t >= 0 else []
        expected = sorted({k for s in spaces if (k := table.layouts.get(layout.get(s) or "")) is not None})
        if expected:
            right.append(kind in expected)
        rooms[f"R({e})"] = {"kind": kind, "confidence": float(g.room_kind_confidence[e]) if kind else None,
                            "true": truth.names[t] if t >= 0 else None, "expected": expected or None}
    return {"accuracy": float(np.mean(right)) if right else None, "scored": len(right), "rooms": rooms}


def scene_graph_metrics(g: SceneGraph, world_or_scenario: World | ScenarioConfig,
                        T_world_map: np.ndarray | None = None, resolution: float = 0.2,
                        coverage_radius: float = 1.0) -> dict[str, Any]:
    """The ``results.json["scene_graph"]`` figures of one graph (see module docstring)."""
    T = np.eye(4) if T_world_map is None else np.asarray(T_world_map, dtype=np.float64)
    world = as_world(world_or_scenario)
    truth = true_rooms(world)
    grid = world.gt_voxel_grid(resolution)
    centers = grid.centers()
    free = grid.labels == 0
    overlap, tsize, esize = room_overlap(g, truth, centers[free], T, resolution)
    best_t = overlap.max(axis=1) if overlap.shape[1] else np.zeros(len(truth))
    best_e = overlap.max(axis=0) if overlap.shape[0] else np.zeros(0)
    recall = float(best_t.sum() / tsize.sum()) if tsize.sum() else 0.0
    precision = float(best_e.sum() / esize.sum()) if esize.sum() else 0.0
    seen_t, seen_e = tsize > 0, esize > 0
    recall_mean = float(np.mean(best_t[seen_t] / tsize[seen_t])) if seen_t.any() else 0.0
    precision_mean = float(np.mean(best_e[seen_e] / esize[seen_e])) if seen_e.any() else 0.0
    match = np.where(seen_e, np.argmax(overlap, axis=0), -1) if overlap.shape[1] else np.zeros(0, np.int64)
    # objects
    acc: float | None = None
    if len(g.object_ids):
        t_obj = truth.containing(transform_points(T, g.object_pos))
        e_obj = g.object_room()
        scored = t_obj >= 0
        est_t = np.where(e_obj >= 0, match[np.maximum(e_obj, 0)] if len(match) else -1, -1)
        acc = float(np.mean(est_t[scored] == t_obj[scored])) if scored.any() else None
    # places: free floor cells near a place (horizontal distance)
    k0 = int(grid.index(np.array([[0.0, 0.0, world.floor_z + 1.5 * resolution]]))[0, 2])
    floor = centers[:, :, k0][free[:, :, k0]]
    floor = floor[truth.containing(floor) >= 0]
    coverage = 0.0
    if len(floor) and len(g.place_ids):
        P = transform_points(T, g.place_pos)
        d, _ = cKDTree(P[:, :2]).query(floor[:, :2])
        coverage = float(np.mean(d <= coverage_radius))
    return {
        "room_kinds": room_kind_scores(g, world, truth, match),
        "rooms_found": int(g.num_rooms),
        "rooms_true": len(truth),
        "room_precision": precision,
        "room_recall": recall,
        "room_precision_mean": precision_mean,
        "room_recall_mean": recall_mean,
        "room_match": {f"R({e})": truth.names[t] if t >= 0 else None for e, t in enumerate(match.tolist())},
        "object_room_accuracy": acc,
        "place_coverage": coverage,
        "nodes_per_layer": g.nodes_per_layer(),
        "build_s": float(g.metadata.get("build_s", 0.0)),
        "delta": g.metadata.get("delta"),
    }
