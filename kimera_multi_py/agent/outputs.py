"""A robot's outcome: what it ends a run with, as data and as the files in ``DIR/robotI/``.

:func:`outcome_of` takes it from a live node; :func:`write_outcome` writes it; :func:`read_outcome`
reads it back, so the evaluator (:mod:`kimera_multi_py.eval.team`) scores a single-process
simulation and N agent processes from the same data. Files (docs/deployment.md):

* ``trajectory.tum``: keyframe stamps and estimated poses (team frame once aligned);
* ``map.bt`` (OctoMap, maximum-likelihood occupancy), ``map.ply`` (occupied leaves coloured by
  class) and ``map.kmo`` (our lossless semantic octree, :mod:`kimera_multi_py.mapping.octree_io`);
* ``objects.json``: confirmed object landmarks (class, centroid, axis-aligned box, sightings);
* ``team_objects.json`` (with object sharing): the robot's team object map, every robot's objects
  fused, with team ids (``source << 24 | landmark id``) and the ``members`` fused into each;
* ``graph.g2o``: the robot's own pose graph (odometry and intra-robot closures);
* ``closures.json``: every closure it verified (inter- and intra-robot) with its PCM decision and
  its back-end weight, and the front end's counters;
* ``traffic.json``: bytes and messages per topic, sent and received, and refused messages;
* ``people.json``: the robot's confirmed people tracks (estimate frame), what each keyframe detected
  and the track each detection went to, the dropped detections by reason, and (with people sharing)
  ``team``: the team's fused people (docs/algorithms/people.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.core.errors import DatasetError, MapError
from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.posegraph import PoseGraph, robot_key, split_key
from kimera_multi_py.io.g2o import write_g2o
from kimera_multi_py.io.tum import read_tum, write_tum
from kimera_multi_py.mapping.octree_io import export_bt, export_ply, load_octree, save_octree
from kimera_multi_py.mapping.semantic_octree import SemanticOctree

OUTCOME_VERSION = 1


@dataclass
class ClosureRow:
    own_kf: int
    peer: int
    peer_kf: int
    Z: np.ndarray
    accepted: bool  # by PCM
    weight: float | None  # back-end (GNC) weight, None when the back end never saw it


@dataclass
class RobotOutcome:
    robot: int
    stamps: np.ndarray
    poses: np.ndarray  # (n, 4, 4) estimate
    octree: SemanticOctree
    objects: list[dict[str, Any]]  # class, centroid, lo, hi, sightings
    closures: list[ClosureRow]
    front_end: dict[str, int]
    traffic: dict[str, Any] = field(default_factory=dict)
    pgo_epochs: int = 0
    # the frame decision of the last PGO epoch (pgo.frame_decision.FrameDecision.alignment; in centralised
    # mode the server's, from its settled flag): status (root / aligned / excluded / unaligned),
    # hypothesis, support (places), margin, reason; and frame (the root robot of the poses' frame)
    alignment: dict[str, Any] = field(default_factory=dict)
    # the robot's team object map (object sharing, exact map consensus): fused objects with team
    # ids (source << 24 | landmark id) and ``members``; None without object sharing
    team_objects: list[dict[str, Any]] | None = None
    # people (docs/algorithms/people.md): ``tracks`` (own, confirmed), ``keyframes`` (detections and
    # their tracks), ``dropped``, and ``team`` (the fused team people, None without sharing)
    people: dict[str, Any] = field(default_factory=dict)


def _weights(node: Any) -> dict[tuple[int, int, int], float]:
    """Back-end weights of the closures this robot verified, from its last PGO epoch."""
    pgo = getattr(getattr(node, "pgo", None), "last_pgo", None)
    out: dict[tuple[int, int, int], float] = {}
    if pgo is None:
        return out
    lg = pgo.local
    for e in range(len(lg.inter_own)):
        out[(int(lg.inter_own[e]), int(lg.inter_peer[e]), split_key(int(lg.inter_peer_key[e]))[1])] = \
            float(pgo.state.inter_weights[e])
    for e in np.flatnonzero(~lg.intra_odometry).tolist():
        out[(int(lg.intra_i[e]), node.robot, int(lg.intra_j[e]))] = float(pgo.state.intra_weights[e])
    return out


def outcome_of(node: Any, server_weights: dict[tuple[int, int, int, int], float] | None = None) -> RobotOutcome:
    """The outcome of a live :class:`~kimera_multi_py.agent.node.AgentNode`. In centralised mode
    the back-end weights come from the server (``(a, kf_a, b, kf_b) -> w``)."""
    agent: Agent = node.agent
    weights = _weights(node)
    rows = []
    for peer, group in sorted(agent.closures.items()):
        for c in group:
            if server_weights is not None:
                w = server_weights.get((agent.robot, c.own_kf, peer, c.peer_kf))
            else:
                w = weights.get((c.own_kf, peer, c.peer_kf))
            rows.append(ClosureRow(c.own_kf, peer, c.peer_kf, np.array(c.Z), c.accepted, w))
    objects = []
    for lm in agent.objects.confirmed():
        lo, hi = lm.aabb()
        objects.append({"id": int(lm.id), "class": int(lm.label), "centroid": [float(v) for v in lm.position],
                        "lo": [float(v) for v in lo], "hi": [float(v) for v in hi],
                        "sightings": int(lm.num_observations)})
    s = agent.stats
    traffic = {"counters": node.bus.counters.snapshot(), "refused": dict(node.errors)}
    epochs = node.pgo.stats.epochs if getattr(node, "pgo", None) is not None else 0
    # the frame decision (the last PGO epoch's, or the server's) and ``frame``: the root robot of
    # the frame the poses are in (own id: its own frame)
    alignment = dict(getattr(node, "alignment", {}) or {})
    sharing = getattr(node, "objects", None)
    people_sharing = getattr(node, "people", None)
    tracker = agent.people
    people = {"tracks": tracker.people(), "dropped": dict(tracker.dropped),
              "keyframes": [{"index": r.index, "stamp": r.stamp, "tracks": r.tracks.tolist(),
                             "detections": transform_points(tracker.correction(r.submap), r.refs).tolist()}
                            for r in tracker.log],
              "team": None if people_sharing is None else people_sharing.team_people()}
    return RobotOutcome(agent.robot, np.array(agent.stamps), np.array(agent.poses).reshape(-1, 4, 4),
                        agent.map.octree, objects, rows,
                        {"candidates": s.candidates, "verified": s.verified,
                         "rejected_verification": s.rejected_verification,
                         "rejected_view_angle": s.rejected_view_angle}, traffic, epochs, alignment,
                        None if sharing is None else sharing.team_objects(), people)


def own_graph(agent: Agent) -> PoseGraph:
    """The robot's own pose graph at its current estimate."""
    i, j, Z, info, _ = agent.intra_edges()
    n = agent.num_keyframes
    return PoseGraph(poses=np.array(agent.poses).reshape(-1, 4, 4), robot=np.full(n, agent.robot),
                     local=np.arange(n), ids=np.array([robot_key(agent.robot, k) for k in range(n)], dtype=np.int64),
                     edge_i=i, edge_j=j, measurement=Z, information=info, source=f"robot{agent.robot}")


def write_outcome(out_dir: str | Path, outcome: RobotOutcome, graph: PoseGraph | None = None) -> Path:
    """Write ``out_dir/robotI/`` (see the module docstring); return that folder."""
    d = Path(out_dir) / f"robot{outcome.robot}"
    d.mkdir(parents=True, exist_ok=True)
    write_tum(d / "trajectory.tum", outcome.stamps, outcome.poses)
    save_octree(outcome.octree, d / "map.kmo")
    export_bt(outcome.octree, d / "map.bt")
    export_ply(outcome.octree, d / "map.ply")
    _write_json(d / "objects.json", {"version": OUTCOME_VERSION, "robot": outcome.robot, "frame": "estimate",
                                     "objects": outcome.objects})
    if outcome.team_objects is not None:
        _write_json(d / "team_objects.json", {"version": OUTCOME_VERSION, "robot": outcome.robot,
                                              "frame": "estimate", "objects": outcome.team_objects})
    _write_json(d / "closures.json", {
        "version": OUTCOME_VERSION, "robot": outcome.robot, "front_end": outcome.front_end,
        "pgo_epochs": outcome.pgo_epochs, "alignment": outcome.alignment,
        "closures": [{"own_kf": c.own_kf, "peer": c.peer, "peer_kf": c.peer_kf, "Z": c.Z.tolist(),
                      "accepted": c.accepted, "weight": c.weight} for c in outcome.closures]})
    _write_json(d / "traffic.json", outcome.traffic)
    _write_json(d / "people.json", {"version": OUTCOME_VERSION, "robot": outcome.robot, "frame": "estimate",
                                    **outcome.people})
    if graph is not None:
        write_g2o(d / "graph.g2o", graph)
    return d


def _write_json(path: Path, data: Any) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    tmp.replace(path)


def _read_json(path: Path) -> Any:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise DatasetError(f"{path}: unreadable ({exc})") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: not a JSON object")
    return data


def read_outcome(run_dir: str | Path, robot: int) -> RobotOutcome:
    """Read ``run_dir/robotI/`` back (any missing or corrupt file raises DatasetError)."""
    d = Path(run_dir) / f"robot{robot}"
    if not d.is_dir():
        raise DatasetError(f"{d}: no outputs of robot {robot}")
    stamps, poses = read_tum(d / "trajectory.tum")
    try:
        octree = load_octree(d / "map.kmo")
    except (OSError, MapError) as exc:
        raise DatasetError(f"{d / 'map.kmo'}: {exc}") from None
    objs = _read_json(d / "objects.json")
    cl = _read_json(d / "closures.json")
    traffic = _read_json(d / "traffic.json") if (d / "traffic.json").exists() else {}
    team_objs = _read_json(d / "team_objects.json") if (d / "team_objects.json").exists() else None
    people = _read_json(d / "people.json") if (d / "people.json").exists() else {}
    try:
        rows = [ClosureRow(int(c["own_kf"]), int(c["peer"]), int(c["peer_kf"]), np.array(c["Z"], dtype=float),
                           bool(c["accepted"]), None if c["weight"] is None else float(c["weight"]))
                for c in cl["closures"]]
        return RobotOutcome(robot, stamps, poses, octree, list(objs["objects"]), rows,
                            {k: int(v) for k, v in cl["front_end"].items()}, traffic, int(cl.get("pgo_epochs", 0)),
                            dict(cl.get("alignment") or {}),
                            None if team_objs is None else list(team_objs["objects"]),
                            {k: people[k] for k in ("tracks", "keyframes", "dropped", "team") if k in people})
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{d}: malformed outputs ({exc!r})") from None
