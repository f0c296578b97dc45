"""People against the simulator's truth: ``results.json["people"]`` (docs/algorithms/people.md).

Visibility
    A true person is in view of a keyframe when at least ``min_hits`` of the sensor's rays reach
    them first (the rays of the sensor's pattern that pass near the person are cast against the
    world and every person; a ray that stops at another person in front of them does not count).
Detection
    Per keyframe, detections (estimate frame, placed in the world through ``T_world_team``) and
    the true people are matched by ``scipy.optimize.linear_sum_assignment`` within ``match_distance``
    (horizontal). ``precision`` = matched / detections; ``recall`` = matched people in view / people
    in view; pooled over every keyframe of every robot in the team frame, with the per-keyframe means.
Tracking
    ``motmetrics`` (CLEAR MOT): per robot, frames are its keyframes, objects the people in view and
    hypotheses the samples of its confirmed tracks at that keyframe (squared-distance gate
    ``match_distance``^2); ``mota``, ``num_switches`` and the rest, per robot and overall.
    ``mot_team_ids``: the same with each track named by the team person it was fused into (the ids
    the robot's scene graph gives), where another robot's track may bridge a gap.
Trajectories
    The team's people (every robot's tracks fused, :func:`~kimera_multi_py.people.fusion.fuse_people`)
    in the world. ``trajectory_rmse``: per true person, the RMSE of the horizontal position of every
    tracked sample nearest to that person at its stamp (how well a track places the person it is
    on). ``trajectory_rmse_whole_tracks``: each fused person stands for the true person nearest to
    it over the whole track (median distance), and every sample counts against that person's path:
    a track that swapped people (an ID error, also in ``mot``) carries the distance between them.
Rooms
    ``room_occupancy_accuracy``: the share of the team graph's person samples whose room (through
    the graph's room match, as objects are scored) is the true room of the true person at that stamp.
Agreement
    ``ids_agree``: every robot's team people have the same ids; ``ids`` per robot.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from kimera_multi_py.agent.outputs import RobotOutcome
from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.eval.scene_graph_truth import true_rooms
from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.people.fusion import TeamTrack, fuse_people
from kimera_multi_py.scene_graph.graph import SceneGraph
from kimera_multi_py.sim.simulation import Simulation

_HUMAN = CLASS_IDS["human"]


def people_in_view(sim: Simulation, pose: np.ndarray, stamp: float, min_hits: int = 15) -> np.ndarray:
    """Indices of the true people at least ``min_hits`` rays of a keyframe taken at ``pose`` reach."""
    humans = sim.humans_at(stamp)
    if len(humans) == 0:
        return np.zeros(0, dtype=np.int64)
    R, t = pose[:3, :3], pose[:3, 3]
    dirs = sim.sensor.directions @ R.T
    rel = humans.center[:, None, :2] - t[None, None, :2]  # (h, 1, 2)
    dxy = dirs[None, :, :2]
    norm2 = np.maximum(np.sum(dxy ** 2, axis=2), 1e-12)
    s = np.sum(rel * dxy, axis=2) / norm2  # ray parameter of the closest approach to each axis
    off = np.linalg.norm(rel - s[..., None] * dxy, axis=2)
    z = t[2] + s * dirs[None, :, 2]
    near = (s > 0) & (off <= humans.half[:, None, 0] + 0.05) & (np.abs(z - humans.center[:, None, 2])
                                                                 <= humans.half[:, None, 2] + 0.05)
    owner, ray = np.nonzero(near)
    if len(ray) == 0:
        return np.zeros(0, dtype=np.int64)
    ranges, labels = sim.world.raycast(t, dirs[ray], sim.sensor.max_range, humans)
    # the ray stops at this person, not at another one in front of them: horizontally, the hit lies
    # no nearer than the person's near side (the closest approach to their axis less their radius)
    flat = np.sqrt(norm2[0, ray])  # horizontal length per unit of range
    at = ranges * flat >= s[owner, ray] * flat - humans.half[owner, 0] - 0.05
    hits = np.bincount(owner[(labels == _HUMAN) & at], minlength=len(humans))
    return np.flatnonzero(hits >= min_hits)


def _truth_at(sim: Simulation, stamps: np.ndarray) -> np.ndarray:
    """True positions (people, len(stamps), 3)."""
    out = np.zeros((len(sim.humans), len(stamps), 3))
    for j, h in enumerate(sim.humans):
        out[j] = [h.position(float(t)) for t in stamps]
    return out


def _match(a: np.ndarray, b: np.ndarray, gate: float) -> list[tuple[int, int]]:
    if len(a) == 0 or len(b) == 0:
        return []
    d = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=2)
    rows, cols = linear_sum_assignment(np.where(d <= gate, d, 1e6))
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if d[r, c] <= gate]


def _mot(accs: dict[str, Any]) -> dict[str, Any]:
    import motmetrics as mm

    names = sorted(accs)
    if not names:
        return {}
    keys = ["mota", "motp", "num_switches", "num_false_positives", "num_misses", "num_objects",
            "num_unique_objects", "precision", "recall"]
    summary = mm.metrics.create().compute_many([accs[n] for n in names], metrics=keys, names=names,
                                               generate_overall=True)
    out = {}
    for row, vals in summary.to_dict(orient="index").items():
        out["overall" if row == "OVERALL" else str(row)] = {k: _num(v) for k, v in vals.items()}
    return out


def _num(v: Any) -> Any:
    v = float(v)
    return None if not np.isfinite(v) else (int(v) if v.is_integer() else v)


def people_results(sim: Simulation, truth: Sequence[np.ndarray], outcomes: Sequence[RobotOutcome],
                   T_world_team: np.ndarray, in_frame: Sequence[int], team_graph: SceneGraph | None = None,
                   room_match: Mapping[str, str | None] | None = None, match_distance: float = 0.5,
                   min_hits: int = 15) -> dict[str, Any]:
    """``results.json["people"]`` (see the module docstring); only robots in ``in_frame`` are scored."""
    import motmetrics as mm

    T = np.asarray(T_world_team, dtype=np.float64)
    team = [o for o in outcomes if o.robot in set(in_frame) and o.people.get("keyframes") is not None]
    tp = fp = seen = found = 0
    per_kf_p, per_kf_r = [], []
    accs: dict[str, Any] = {}
    team_accs: dict[str, Any] = {}
    dropped: dict[str, int] = {}
    for o in team:
        samples = {(int(t["id"]), float(s)): p for t in o.people.get("tracks", [])
                   for s, p in zip(t["stamps"], t["positions"], strict=True)}
        acc, team_acc = mm.MOTAccumulator(auto_id=True), mm.MOTAccumulator(auto_id=True)
        fused = {int(m): int(p["id"]) for p in (o.people.get("team") or []) for m in p.get("members", [])}
        for k, v in o.people.get("dropped", {}).items():
            dropped[k] = dropped.get(k, 0) + int(v)
        for rec in o.people["keyframes"]:
            stamp, idx = float(rec["stamp"]), int(rec["index"])
            if idx >= len(truth[o.robot]):
                continue
            true_xyz = _truth_at(sim, np.array([stamp]))[:, 0]
            view = people_in_view(sim, truth[o.robot][idx], stamp, min_hits)
            dets = transform_points(T, np.asarray(rec["detections"], dtype=np.float64).reshape(-1, 3))
            pairs = _match(dets, true_xyz, match_distance)
            hit_view = sum(1 for _, j in pairs if j in set(view.tolist()))
            tp += len(pairs)
            fp += len(dets) - len(pairs)
            seen += len(view)
            found += hit_view
            if len(dets):
                per_kf_p.append(len(pairs) / len(dets))
            if len(view):
                per_kf_r.append(hit_view / len(view))
            hyp = [(int(tr), samples[(int(tr), stamp)]) for tr in rec["tracks"] if (int(tr), stamp) in samples]
            hyp_xyz = transform_points(T, np.array([p for _, p in hyp], dtype=np.float64).reshape(-1, 3))
            dist = np.asarray(mm.distances.norm2squared_matrix(true_xyz[view][:, :2], hyp_xyz[:, :2],
                                                               max_d2=match_distance ** 2)).reshape(len(view), len(hyp))
            acc.update(view.tolist(), [h for h, _ in hyp], dist)
            names = [fused.get(team_id(o.robot, h), team_id(o.robot, h)) for h, _ in hyp]
            once = [i for i, h in enumerate(names) if h not in names[:i]]
            team_acc.update(view.tolist(), [names[i] for i in once], dist[:, once])
        accs[str(o.robot)] = acc
        team_accs[str(o.robot)] = team_acc
    mot = _mot(accs)
    overall = mot.get("overall", {})
    people = overall.get("num_unique_objects") or 0
    out: dict[str, Any] = {
        "robots_scored": [o.robot for o in team],
        "detection": {"precision": tp / (tp + fp) if tp + fp else None, "recall": found / seen if seen else None,
                      "precision_per_keyframe_mean": float(np.mean(per_kf_p)) if per_kf_p else None,
                      "recall_per_keyframe_mean": float(np.mean(per_kf_r)) if per_kf_r else None,
                      "detections": tp + fp, "people_in_view": seen, "dropped": dropped},
        "mot": mot,
        "mot_team_ids": _mot(team_accs),
        "mota": overall.get("mota"),
        "id_switches": overall.get("num_switches"),
        "id_switches_per_person": (overall.get("num_switches", 0) / people) if people else None,
    }
    out.update(_trajectories(sim, team, T, match_distance))
    if team_graph is not None and room_match is not None:
        out["room_occupancy_accuracy"] = _occupancy(sim, team_graph, T, room_match)
    ids = {str(o.robot): sorted(int(p["id"]) for p in o.people["team"]) for o in outcomes
           if o.people.get("team") is not None}
    out["ids"] = ids
    out["ids_agree"] = len({tuple(v) for v in ids.values()}) <= 1 if ids else None
    return out


def _trajectories(sim: Simulation, team: Sequence[RobotOutcome], T: np.ndarray, gate: float) -> dict[str, Any]:
    tracks = {team_id(o.robot, int(t["id"])): TeamTrack(o.robot, np.asarray(t["stamps"], np.float64),
                                                        np.asarray(t["positions"], np.float64).reshape(-1, 3))
              for o in team for t in o.people.get("tracks", [])}
    fused = fuse_people(tracks)
    err2: dict[int, list[np.ndarray]] = {}  # per true person: squared errors of the samples nearest them
    whole: dict[int, list[np.ndarray]] = {}  # per true person: of the whole tracks that follow them most
    assigned = {}
    for p in fused:
        st = np.asarray(p["stamps"], np.float64)
        xyz = transform_points(T, np.asarray(p["positions"], np.float64).reshape(-1, 3))
        true = _truth_at(sim, st)  # (h, n, 3)
        d = np.linalg.norm(true[:, :, :2] - xyz[None, :, :2], axis=2)
        j = int(np.argmin(np.median(d, axis=1)))
        assigned[int(p["id"])] = j
        whole.setdefault(j, []).append(d[j] ** 2)
        near = np.argmin(d, axis=0)
        for h in np.unique(near).tolist():
            err2.setdefault(h, []).append(d[h, near == h] ** 2)
    rmse = {f"human{j}": float(np.sqrt(np.mean(np.concatenate(e)))) for j, e in sorted(err2.items())}
    rmse_whole = {f"human{j}": float(np.sqrt(np.mean(np.concatenate(e)))) for j, e in sorted(whole.items())}
    return {"people_true": len(sim.humans), "people_tracked": len(fused),
            "people_per_human": {f"human{j}": sum(1 for v in assigned.values() if v == j) for j in sorted(whole)},
            "trajectory_rmse": rmse, "trajectory_rmse_max": max(rmse.values()) if rmse else None,
            "trajectory_rmse_whole_tracks": rmse_whole,
            "trajectory_rmse_whole_tracks_max": max(rmse_whole.values()) if rmse_whole else None}


def _occupancy(sim: Simulation, g: SceneGraph, T: np.ndarray, room_match: Mapping[str, str | None]) -> float | None:
    if len(g.person_id) == 0:
        return None
    rooms = true_rooms(sim.world)
    est = g.person_room()
    xyz = transform_points(T, g.person_pos)
    right = []
    for pid in np.unique(g.person_id).tolist():
        m = g.person_id == pid
        true = _truth_at(sim, g.person_stamp[m])
        d = np.linalg.norm(true[:, :, :2] - xyz[m][None, :, :2], axis=2)
        j = int(np.argmin(np.median(d, axis=1)))
        t_room = rooms.containing(true[j])
        names = [room_match.get(f"R({r})") if r >= 0 else None for r in est[m].tolist()]
        right += [t >= 0 and n == rooms.names[t] for t, n in zip(t_room.tolist(), names, strict=True)]
    return float(np.mean(right)) if right else None
