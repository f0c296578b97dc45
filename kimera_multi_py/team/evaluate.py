"""Evaluate a run folder written by agent processes (``DIR/robotI/``, ``DIR/server/``) against
the simulator's ground truth, into the same :class:`Results` schema as ``kimera-multi sim``; or,
on recorded data, against what ground truth there is (:func:`recorded_scores`, docs/bags.md)."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from kimera_multi_py.agent.outputs import RobotOutcome, read_outcome
from kimera_multi_py.core.errors import DatasetError, MapError
from kimera_multi_py.eval.people import people_results
from kimera_multi_py.eval.results import Results, RobotResult
from kimera_multi_py.eval.slam import map_quality
from kimera_multi_py.eval.team import (
    alignment_report,
    closure_stats,
    excluded_robots,
    scene_graph_results,
    team_frame_robots,
    team_results,
    traffic_totals,
    trajectory_results,
)
from kimera_multi_py.io.tum import write_tum
from kimera_multi_py.mapping.octree_io import load_octree
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.mapshare.fusion import octree_cells
from kimera_multi_py.scene_graph.graph import SceneGraph
from kimera_multi_py.sim.scenario import ScenarioConfig
from kimera_multi_py.sim.simulation import Simulation
from kimera_multi_py.team.build import agent_params
from kimera_multi_py.team.config import KimeraConfig


def _server_weights(run_dir: Path) -> dict[tuple[int, int, int, int], float] | None:
    path = run_dir / "server" / "weights.json"
    if not path.exists():
        return None
    try:
        rows = json.loads(path.read_text())["weights"]
        return {(int(a), int(ka), int(b), int(kb)): float(w) for a, ka, b, kb, w in rows}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{path}: malformed server weights ({exc!r})") from None


def _team_maps(run_dir: Path, robots: list[int]) -> dict[int, SemanticOctree]:
    out = {}
    for r in robots:
        path = run_dir / f"robot{r}" / "team_map.kmo"
        if path.exists():
            try:
                out[r] = load_octree(path)
            except MapError as exc:
                raise DatasetError(f"{path}: {exc}") from None
    return out


def team_map_figures(world: object | None, maps: dict[int, SemanticOctree], T: np.ndarray) -> dict[str, object]:
    """Each robot's team map against the truth (with a ``world``), and how far the robots' team
    maps agree (the fraction of robot 0's cells whose values another robot holds identically)."""
    first = min(maps)
    ref_codes, ref_rows = octree_cells(maps[first])
    same = {}
    for r, tree in sorted(maps.items()):
        codes, rows = octree_cells(tree)
        common, ia, ib = np.intersect1d(ref_codes, codes, return_indices=True)
        equal = np.all(ref_rows[ia] == rows[ib], axis=1).sum() if len(common) else 0
        same[str(r)] = float(equal / max(len(ref_codes), len(codes), 1))
    out: dict[str, object] = {f"identical_to_robot{first}": same,
                              "agree": len(maps) > 1 and all(v == 1.0 for v in same.values()),
                              "team_cells": {str(r): int(len(octree_cells(t)[0])) for r, t in sorted(maps.items())}}
    if world is not None:
        grid = world.gt_voxel_grid(next(iter(maps.values())).resolution)  # type: ignore[attr-defined]
        centers, gt = grid.centers().reshape(-1, 3), grid.labels.reshape(-1)
        out["team_map"] = {str(r): map_quality(t, T, centers, gt) for r, t in sorted(maps.items())}
    return out


def linger_reports(run_dir: Path, robots: list[int]) -> dict[str, object]:
    """Each robot's ``linger.json`` (team/process.py): whether its team map was whole when it
    exited, how long it waited, and what it was missing."""
    out: dict[str, object] = {}
    for r in robots:
        path = run_dir / f"robot{r}" / "linger.json"
        if path.exists():
            try:
                out[str(r)] = json.loads(path.read_text())
            except (OSError, ValueError) as exc:
                raise DatasetError(f"{path}: {exc}") from None
    return out


def link_reports(run_dir: Path, robots: list[int]) -> dict[str, object]:
    """Under a link budget, each robot's (and the server's) ``links.json`` (team/process.py) merged:
    the budget and every process's link figures (bytes, queue delay, dropped, still queued at its exit)."""
    out: dict[str, object] = {}
    links: dict[str, object] = {}
    for folder in [f"robot{r}" for r in robots] + ["server"]:
        path = run_dir / folder / "links.json"
        if path.exists():
            try:
                rep = json.loads(path.read_text())
                links.update(rep["links"])
                out.update(kbps=rep["kbps"], policy=rep["policy"])
            except (OSError, ValueError, KeyError, TypeError) as exc:
                raise DatasetError(f"{path}: {exc}") from None
    if links:
        out["links"] = links
    return out


def _checked(run_dir: Path, outcomes: list[RobotOutcome], mode: str, keyframes: Sequence[int]) -> None:
    """Every robot processed its ``keyframes``; the server's closure weights onto the closures."""
    weights = _server_weights(run_dir)
    if mode == "centralized" and weights is None:
        raise DatasetError(f"{run_dir / 'server' / 'weights.json'}: missing (did the server finish?)")
    if weights is not None:
        for o in outcomes:
            for c in o.closures:
                c.weight = weights.get((o.robot, c.own_kf, c.peer, c.peer_kf))
    for o, n in zip(outcomes, keyframes, strict=True):
        if len(o.poses) != n:
            raise DatasetError(f"{run_dir / f'robot{o.robot}' / 'trajectory.tum'}: {len(o.poses)} keyframes, "
                               f"its source has {n}")


def closure_counts(outcomes: Sequence[RobotOutcome]) -> dict[str, int]:
    """Loop closures through the pipeline without truth: :func:`closure_stats`'s counts that need
    no true poses (accepted: kept by PCM and weighted >= 0.5 by the back end's GNC)."""
    rows = [(c.peer != o.robot, c.accepted, c.accepted and (c.weight or 0.0) >= 0.5)
            for o in outcomes for c in o.closures]
    inter, pcm_ok, final = np.array(rows, dtype=bool).reshape(-1, 3).T
    fe = [o.front_end for o in outcomes]
    return {"candidates": sum(s["candidates"] for s in fe), "verified": sum(s["verified"] for s in fe),
            "rejected_verification": sum(s["rejected_verification"] for s in fe),
            "rejected_view_angle": sum(s.get("rejected_view_angle", 0) for s in fe),
            "rejected_pcm_inter": int((inter & ~pcm_ok).sum()),
            "rejected_gnc_inter": int((inter & pcm_ok & ~final).sum()),
            "accepted_inter": int((inter & final).sum()), "accepted_intra": int((~inter & final).sum())}


def recorded_scores(truth: Sequence[np.ndarray] | None, est: Sequence[np.ndarray],
                    outcomes: Sequence[RobotOutcome]) -> tuple[list[RobotResult], dict[str, Any], np.ndarray,
                                                               dict[str, Any]]:
    """What ``truth`` (per robot its true poses, or None: unknown) allows without the world:
    ``(robots, team, T_world_team, extra)`` with trajectories and, after a team run (``outcomes``),
    closures, alignment and traffic. Without truth, ATE is NaN and closures are only counted."""
    extra: dict[str, Any] = {"ground_truth": truth is not None}
    if truth is not None:
        robots, team, T = trajectory_results(list(truth), list(est), anchored=not outcomes)
    else:
        robots = [RobotResult(i, len(e), float(np.linalg.norm(np.diff(e[:, :3, 3], axis=0), axis=1).sum()),
                              math.nan) for i, e in enumerate(est)]
        team = {"ate_rmse_m": math.nan, "keyframes": sum(r.keyframes for r in robots),
                "trajectory_length_m": sum(r.trajectory_length_m for r in robots), "frames": "no ground truth"}
        T = np.eye(4)
    if outcomes:
        extra["loop_closures"] = (closure_stats(list(truth), list(outcomes)) if truth is not None
                                  else closure_counts(outcomes))
        extra.update(alignment=alignment_report(list(outcomes)), bytes_sent=traffic_totals(list(outcomes)))
    return robots, team, T, extra


def evaluate_recorded_run(run_dir: str | Path, truth: Sequence[np.ndarray | None], keyframes: Sequence[int],
                          name: str, mode: str, wall_s: float, world: Any = None,
                          object_sightings: int = 1) -> Results:
    """The results of agent processes on recorded data: ``truth`` per robot (None: unknown; the
    run is scored against truth only when every robot has it), ``keyframes`` each robot's source
    holds. The robots' team maps are compared with each other; with truth and the simulated
    ``world`` the data came from, maps and objects (seen ``object_sightings`` times) are also
    scored against it, as :func:`evaluate_run` scores them."""
    run_dir = Path(run_dir)
    outcomes = [read_outcome(run_dir, r) for r in range(len(keyframes))]
    _checked(run_dir, outcomes, mode, keyframes)
    known = None if any(t is None for t in truth) else [np.asarray(t) for t in truth]
    robots, team, T, extra = recorded_scores(known, [o.poses for o in outcomes], outcomes)
    world = world if known is not None else None
    if world is not None and known is not None:
        extra.update(team_results(world, known, outcomes, T, object_sightings))
    extra["pgo_runs"] = max(o.pgo_epochs for o in outcomes)
    extra["transport"] = "zenoh-processes"
    if team_maps := _team_maps(run_dir, [o.robot for o in outcomes]):
        extra["map_consensus"] = team_map_figures(world, team_maps, T)
    if lingered := linger_reports(run_dir, [o.robot for o in outcomes]):
        extra["linger"] = lingered
    if links := link_reports(run_dir, [o.robot for o in outcomes]):
        extra["link_budget"] = links
    for o, true in zip(outcomes, truth, strict=True):
        if true is not None:
            write_tum(run_dir / f"robot{o.robot}_gt.tum", o.stamps, np.asarray(true))
    starts = [float(o.stamps[0]) for o in outcomes if len(o.stamps)]
    ends = [float(o.stamps[-1]) for o in outcomes if len(o.stamps)]
    return Results(scenario=name, mode=mode, seed=0, robots=robots, team=team,
                   sim_seconds=max(ends) - min(starts) if starts else 0.0, wall_s=wall_s, extra=extra)


def evaluate_run(run_dir: str | Path, cfg: ScenarioConfig, seed: int, mode: str, wall_s: float,
                 config: KimeraConfig | None = None) -> Results:
    """The run's results (``config``: the team's configuration, default the defaults)."""
    run_dir = Path(run_dir)
    config = config or KimeraConfig.defaults()
    sim = Simulation(cfg, seed)
    truth = [plan.poses for plan in sim.plans]
    outcomes = [read_outcome(run_dir, r) for r in range(sim.num_robots)]
    _checked(run_dir, outcomes, mode, [len(t) for t in truth])
    robots, team, T = trajectory_results(truth, [o.poses for o in outcomes], anchored=False,
                                         own_frame=excluded_robots(outcomes))
    extra: dict[str, object] = dict(team_results(sim.world, truth, outcomes, T,
                                                 agent_params(cfg, config).team_object_sightings))
    extra["pgo_runs"] = max(o.pgo_epochs for o in outcomes)
    extra["transport"] = "zenoh-processes"
    team_maps = _team_maps(run_dir, [o.robot for o in outcomes])
    if team_maps:
        extra["map_consensus"] = team_map_figures(sim.world, team_maps, T)
    if lingered := linger_reports(run_dir, [o.robot for o in outcomes]):
        extra["linger"] = lingered
    if links := link_reports(run_dir, [o.robot for o in outcomes]):
        extra["link_budget"] = links
    graphs: dict[str, object] = {}
    extra["scene_graph"] = scene_graph_results(sim.world, outcomes, T, run_dir, team_maps or None,
                                               params=config.to_scene_graph_params(), graphs=graphs)
    team_graph, room_match = graphs.get("team"), graphs.get("room_match")
    extra["people"] = people_results(sim, truth, outcomes, T, team_frame_robots(outcomes),
                                     team_graph if isinstance(team_graph, SceneGraph) else None,
                                     room_match if isinstance(room_match, dict) else None)
    for r, plan in enumerate(sim.plans):
        write_tum(run_dir / f"robot{r}_gt.tum", np.asarray(plan.stamps), plan.poses)
    return Results(scenario=cfg.name, mode=mode, seed=sim.seed, robots=robots, team=team,
                   sim_seconds=sim.duration, wall_s=wall_s, extra=extra)
