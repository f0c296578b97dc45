"""Scoring a team run against the simulator's ground truth, from the robots' outcomes.

The same function scores a single-process simulation (outcomes taken from live nodes) and a
launch of N agent processes (outcomes read back from ``DIR/robotI/``).
"""

from __future__ import annotations

import json
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.outputs import RobotOutcome
from kimera_multi_py.agent.team_graph import joint_graph
from kimera_multi_py.eval.metrics import align_se3, ate_rmse
from kimera_multi_py.eval.results import RobotResult
from kimera_multi_py.eval.slam import map_quality, merge_objects, object_quality, score_closures, world_boxes
from kimera_multi_py.io.g2o import write_g2o
from kimera_multi_py.scene_graph.params import SceneGraphParams


def team_frame_estimates(truth: Sequence[np.ndarray], estimates: Sequence[np.ndarray],
                         own_frame: Collection[int] = ()) -> list[np.ndarray]:
    """The estimates in the team frame (robot 0's); a robot in ``own_frame`` (kept out of the team
    frame) is anchored like dead reckoning: its first pose placed at its true start."""
    return [np.linalg.inv(truth[0][0]) @ truth[i][0] @ np.linalg.inv(est[0]) @ est if i in own_frame else est
            for i, est in enumerate(estimates)]


def trajectory_results(truth: Sequence[np.ndarray], estimates: Sequence[np.ndarray], anchored: bool,
                       own_frame: Collection[int] = ()) -> tuple[list[RobotResult], dict[str, Any], np.ndarray]:
    """Per-robot and team ATE. ``anchored``: each estimate is in its own odometry frame and is
    anchored at the robot's true start (dead reckoning); otherwise all share the team frame,
    except the robots in ``own_frame`` (kept out of the team frame), anchored like dead reckoning.
    Returns ``(robots, team, T_world_team)``."""
    robots, team_est, team_true = [], [], []
    if not anchored:
        estimates = team_frame_estimates(truth, estimates, own_frame)
    for i, (true, est) in enumerate(zip(truth, estimates, strict=True)):
        if len(est) != len(true):
            raise ValueError(f"robot {i}: {len(est)} estimated poses for {len(true)} true keyframes")
        length = float(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1).sum())
        robots.append(RobotResult(i, len(true), length, ate_rmse(est[:, :3, 3], true[:, :3, 3])))
        team_est.append((true[0] @ est if anchored else est)[:, :3, 3])
        team_true.append(true[:, :3, 3])
    est_all, true_all = np.concatenate(team_est), np.concatenate(team_true)
    team = {
        "ate_rmse_m": ate_rmse(est_all, true_all),
        "keyframes": int(sum(r.keyframes for r in robots)),
        "trajectory_length_m": float(sum(r.trajectory_length_m for r in robots)),
        "frames": ("each robot's odometry anchored at its true start pose" if anchored
                   else "the team frame (robot 0's), one SE(3) alignment to the world"),
    }
    return robots, team, align_se3(est_all, true_all)


def team_results(world: Any, truth: Sequence[np.ndarray], outcomes: Sequence[RobotOutcome],
                 T_world_team: np.ndarray, min_sightings: int) -> dict[str, Any]:
    """Maps, objects, loop closures and traffic of a team run."""
    grid = world.gt_voxel_grid(outcomes[0].octree.resolution)
    centers, gt = grid.centers().reshape(-1, 3), grid.labels.reshape(-1)
    maps = {str(o.robot): map_quality(o.octree, T_world_team, centers, gt) for o in outcomes}
    objs = [ob for o in outcomes for ob in o.objects if ob["sightings"] >= min_sightings]
    lo, hi = world_boxes(T_world_team, np.array([ob["lo"] for ob in objs]).reshape(-1, 3),
                         np.array([ob["hi"] for ob in objs]).reshape(-1, 3))
    cls, lo, hi = merge_objects(np.array([ob["class"] for ob in objs], dtype=int), lo, hi)
    objects: dict[str, Any] = object_quality(cls, (lo + hi) / 2, np.array([o.label for o in world.objects]),
                                             np.array([o.centroid for o in world.objects]))
    objects["landmarks"] = len(objs)
    shared = {o.robot: o.team_objects for o in outcomes if o.team_objects is not None}
    if shared:  # each robot's team object map (object sharing)
        per_robot: dict[str, Any] = {}
        for r, tob in sorted(shared.items()):
            kept = [ob for ob in tob if ob["sightings"] >= min_sightings]
            lo, hi = world_boxes(T_world_team, np.array([ob["lo"] for ob in kept]).reshape(-1, 3),
                                 np.array([ob["hi"] for ob in kept]).reshape(-1, 3))
            q = object_quality(np.array([ob["class"] for ob in kept], dtype=int), (lo + hi) / 2,
                               np.array([o.label for o in world.objects]),
                               np.array([o.centroid for o in world.objects]))
            per_robot[str(r)] = {**q, "objects": len(tob)}
        objects["team_per_robot"] = per_robot
    return {"map": maps, "objects": objects, "loop_closures": closure_stats(truth, outcomes),
            "alignment": alignment_report(outcomes),
            "bytes_sent": traffic_totals(outcomes),
            "refused_messages": {o.robot: dict(o.traffic.get("refused", {})) for o in outcomes}}


def scored_closures(truth: Sequence[np.ndarray], outcomes: Sequence[RobotOutcome]) -> np.ndarray:
    """Every verified loop closure of the team, one boolean row each: ``(inter-robot, PCM
    accepted, accepted after the back end's GNC (weight >= 0.5), true against the true poses)``."""
    rows = []
    for o in outcomes:
        if not o.closures:
            continue
        Z = np.stack([c.Z for c in o.closures])
        ok = score_closures(Z, truth[o.robot][[c.own_kf for c in o.closures]],
                            np.stack([truth[c.peer][c.peer_kf] for c in o.closures]))
        for c, true in zip(o.closures, ok, strict=True):
            w = c.weight if c.weight is not None else 0.0
            rows.append((c.peer != o.robot, c.accepted, c.accepted and w >= 0.5, bool(true)))
    return np.array(rows, dtype=bool).reshape(-1, 4)


def closure_stats(truth: Sequence[np.ndarray], outcomes: Sequence[RobotOutcome]) -> dict[str, int]:
    """Loop closures through the pipeline, scored against the true poses.

    ``candidates`` were fetched and verified; ``verified`` passed geometry; PCM then kept a
    consistent set and the back end's GNC weights decided the rest (weight < 0.5 = rejected).
    """
    r = scored_closures(truth, outcomes)
    inter, pcm_ok, final, true = r.T
    fe = [o.front_end for o in outcomes]
    return {
        "candidates": sum(s["candidates"] for s in fe),
        "verified": sum(s["verified"] for s in fe),
        "rejected_verification": sum(s["rejected_verification"] for s in fe),
        "rejected_view_angle": sum(s.get("rejected_view_angle", 0) for s in fe),
        "verified_true_inter": int((inter & true).sum()),
        "verified_false_inter": int((inter & ~true).sum()),
        "rejected_pcm_true_inter": int((inter & ~pcm_ok & true).sum()),
        "rejected_pcm_false_inter": int((inter & ~pcm_ok & ~true).sum()),
        "rejected_gnc_true_inter": int((inter & pcm_ok & ~final & true).sum()),
        "rejected_gnc_false_inter": int((inter & pcm_ok & ~final & ~true).sum()),
        "accepted_inter": int((inter & final).sum()),
        "true_accepted_inter": int((inter & final & true).sum()),
        "false_accepted_inter": int((inter & final & ~true).sum()),
        "accepted_intra": int((~inter & final).sum()),
        "false_accepted_intra": int((~inter & final & ~true).sum()),
    }


def alignment_report(outcomes: Sequence[RobotOutcome]) -> dict[str, dict[str, Any]]:
    """Per robot, the frame decision of its last PGO epoch: ``status`` (root / aligned /
    excluded: kept out of the team frame, in its own frame), ``hypothesis`` (4x4, own → team
    frame), ``support`` (distinct places its closures come from), ``margin`` (places over the
    runner-up hypothesis), ``reason`` when excluded, ``drift_ratio`` (estimate against its own
    odometry, in units of its drift model)."""
    return {str(o.robot): dict(o.alignment) for o in outcomes}


def excluded_robots(outcomes: Sequence[RobotOutcome]) -> list[int]:
    """Robots whose estimate is not in the team frame (the lowest robot id's): those that kept
    themselves out of it, and those whose frame is another root's (a robot no inter-robot edge
    ever joined to the team reports its own id as ``frame``)."""
    if not outcomes:
        return []
    root = min(o.robot for o in outcomes)
    return [o.robot for o in outcomes
            if o.alignment.get("status") == "excluded" or int(o.alignment.get("frame", root)) != root]


def team_frame_robots(outcomes: Sequence[RobotOutcome]) -> list[int]:
    """Robots whose poses, and so whose submaps and objects, are in the team frame: those not in
    :func:`excluded_robots`, and the root (the lowest id) always, whose own frame is the team frame
    (kept out by its drift check it falls back to its own solution, first pose at the identity:
    the team's maps still take its evidence in that frame)."""
    if not outcomes:
        return []
    root = min(o.robot for o in outcomes)
    out = set(excluded_robots(outcomes))
    return [o.robot for o in outcomes if o.robot == root or o.robot not in out]


def traffic_totals(outcomes: Sequence[RobotOutcome]) -> dict[str, Any]:
    """Bytes sent per robot and per topic, and messages sent per topic (a message's envelope is
    part of its bytes: many small messages cost more than their fields)."""
    per_robot: dict[str, int] = {}
    per_topic: dict[str, int] = {}
    messages: dict[str, int] = {}
    for o in outcomes:
        sent = o.traffic.get("counters", {}).get("sent", {})
        per_robot[str(o.robot)] = int(sum(v["bytes"] for v in sent.values()))
        for topic, v in sent.items():
            per_topic[topic] = per_topic.get(topic, 0) + int(v["bytes"])
            messages[topic] = messages.get(topic, 0) + int(v.get("messages", 0))
    return {"per_robot": per_robot, "per_topic": per_topic, "messages_per_topic": messages,
            "total": sum(per_robot.values())}


def scene_graph_results(world: Any, outcomes: Sequence[RobotOutcome], T_world_team: np.ndarray,
                        out_dir: Path | None, robot_maps: dict[int, Any] | None = None,
                        team_map: Any = None, params: SceneGraphParams | None = None,
                        graphs: dict[str, Any] | None = None) -> dict[str, Any]:
    """Every robot's scene graph (from its team map and team objects when it has them, else its own
    map and objects), and the team's (from the fused team map, with every robot's objects fused
    and every trajectory), scored against
    the simulator's rooms; writes ``robotI/dsg.json`` and ``dsg.json``.

    The top-level figures are the team graph's (or robot 0's without a team map); ``robots`` holds
    each robot's and ``agree`` whether the robots' graphs match. The team graph leaves out the
    objects and trajectories of the robots kept out of the team frame (only those of
    :func:`team_frame_robots`): they are in their own frames. ``graphs``, when given, receives the
    graph the top-level figures are of (``team``) and its ``room_match``."""
    from kimera_multi_py.eval.scene_graph import graphs_agree, scene_graph_and_outputs
    from kimera_multi_py.mapping.object_fusion import fuse_team, team_id
    from kimera_multi_py.people.fusion import TeamTrack, fuse_people

    built, per_robot = [], {}
    for o in outcomes:
        octree = (robot_maps or {}).get(o.robot, o.octree)
        path = out_dir / f"robot{o.robot}" / "dsg.json" if out_dir is not None else None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
        objects = o.team_objects if o.team_objects is not None else o.objects
        people = o.people.get("team") or o.people.get("tracks") or []
        g, fig = scene_graph_and_outputs(octree, T_world_team, objects, {o.robot: (o.stamps, o.poses)}, world, path,
                                         params, people)
        built.append(g)
        per_robot[str(o.robot)] = fig
    out: dict[str, Any] = dict(per_robot[str(outcomes[0].robot)])
    chosen = built[0]
    if team_map is not None:
        in_frame = set(team_frame_robots(outcomes))
        team = [o for o in outcomes if o.robot in in_frame]
        objects = fuse_team({o.robot: o.objects for o in team})
        trajectories = {o.robot: (o.stamps, o.poses) for o in team}
        people = fuse_people({team_id(o.robot, int(t["id"])): TeamTrack(o.robot, np.asarray(t["stamps"], float),
                                                                         np.asarray(t["positions"], float))
                              for o in team for t in o.people.get("tracks", [])})
        chosen, out = scene_graph_and_outputs(team_map, T_world_team, objects, trajectories, world,
                                              out_dir / "dsg.json" if out_dir is not None else None, params, people)
        out = dict(out)
    if graphs is not None:
        graphs.update(team=chosen, room_match=out.get("room_match"))
    out["robots"] = per_robot
    out["agree"] = graphs_agree(built)
    return out


def write_team_graph(out_dir: Path, agents: list[Agent], truth: list[np.ndarray]) -> None:
    """``team_graph.g2o`` (the joint graph) and ``team_graph_truth.json`` (which inter-robot
    edges are true)."""
    graph, inter = joint_graph(agents)
    write_g2o(out_dir / "team_graph.g2o", graph)
    Z = np.array([agents[a].inter_edges[(ka, b, kb)][0] for a, ka, b, kb in inter]).reshape(-1, 4, 4)
    ok = score_closures(Z, np.array([truth[a][ka] for a, ka, _, _ in inter]).reshape(-1, 4, 4),
                        np.array([truth[b][kb] for _, _, b, kb in inter]).reshape(-1, 4, 4))
    (out_dir / "team_graph_truth.json").write_text(json.dumps(
        {"inter_robot_edges": [list(e) for e in inter], "true": ok.tolist(),
         "note": "inter-robot edges follow the odometry and intra-robot edges in team_graph.g2o"}))
