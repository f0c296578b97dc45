"""What a simulated team run reports of its team maps and writes to its run folder
(docs/outputs.md): the map-consensus figures of ``results.json`` and the run's files."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.agent.outputs import RobotOutcome, own_graph, write_outcome
from kimera_multi_py.eval.map_metrics import TeamMapReport, team_map_report
from kimera_multi_py.eval.results import Results
from kimera_multi_py.eval.slam import map_quality
from kimera_multi_py.eval.team import write_team_graph
from kimera_multi_py.io.tum import write_tum
from kimera_multi_py.mapping.octree_io import export_team_map
from kimera_multi_py.mapshare.consensus import MAP_MESSAGES
from kimera_multi_py.mapshare.fusion import octree_cells
from kimera_multi_py.sim.world import World


def map_consensus_results(nodes: list[AgentNode], ref: Any, map_mode: str, report: TeamMapReport,
                          T_world_team: np.ndarray, world: World | None, comm_range: Any,
                          out_dir: Path | None) -> tuple[dict[str, Any], dict[int, Any]]:
    """``results.json["map_consensus"]`` and each robot's team map: agreement with the
    centralised fusion ``ref``, bytes per map topic, and (given the ``world``: quality scores)
    each team map's accuracy; the team maps are exported into ``out_dir``."""
    live = [n for n in nodes if n.maps is not None]
    cells = {n.robot: n.maps.team_cells() for n in live if n.maps is not None}
    map_topics = {m.TOPIC for m in MAP_MESSAGES}
    sent = {n.robot: {t: int(v["bytes"]) for t, v in n.bus.counters.snapshot()["sent"].items()
                      if t in map_topics} for n in live}
    rep = team_map_report(map_mode, report.rounds, cells, octree_cells(ref), (ref.model.lo, ref.model.hi), sent,
                          {n.robot: n.maps.roam_bytes for n in live if n.maps is not None}, report)
    out = rep.to_dict()
    maps = {n.robot: n.maps.team_map for n in live if n.maps is not None}
    if world is not None:
        grid = world.gt_voxel_grid(ref.resolution)
        centers, gt = grid.centers().reshape(-1, 3), grid.labels.reshape(-1)
        out["team_map"] = {str(r): map_quality(t, T_world_team, centers, gt) for r, t in maps.items()}
        out["centralised_fusion"] = map_quality(ref, T_world_team, centers, gt)
    out["comm_range"] = comm_range
    if out_dir is not None:
        for r, t in maps.items():
            export_team_map(t, out_dir / f"robot{r}")
    return out, maps


def write_run(out_dir: Path, tracks: list[Any], outcomes: list[RobotOutcome], nodes: list[AgentNode],
              agents: list[Agent], results: Results) -> None:
    """Each robot's estimated and true trajectory (TUM), its outcome and own graph, the team's
    joint graph (for ``kimera-multi pgo`` and offline study) and ``results.json``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for i, tr in enumerate(tracks):
        est = outcomes[i].poses if outcomes else np.array(tr.est)
        write_tum(out_dir / f"robot{i}_est.tum", np.array(tr.stamps), est)
        write_tum(out_dir / f"robot{i}_gt.tum", np.array(tr.stamps), np.array(tr.true))
    for node, outcome in zip(nodes, outcomes, strict=True):
        write_outcome(out_dir, outcome, own_graph(node.agent))
    if nodes:
        write_team_graph(out_dir, agents, [np.array(tr.true) for tr in tracks])
    results.write_json(out_dir / "results.json")
