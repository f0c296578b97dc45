"""Map consensus on the office simulator: the three modes of one run, against the centralised fusion.

Each robot's :class:`SubmapMap` is built from its keyframes at their true poses, as the agent
integrates them (a new submap every ``keyframes_per_submap`` keyframes, anchored at its first
pose), so every robot is in the world frame from the start. Every ``period`` seconds of
simulated time each mode's robots exchange over an in-memory network (:class:`MapExchange`,
real codec bytes); after the last keyframe the exchange runs ``--tail`` more seconds. The
reference is the centralised fusion of all evidence, and ROAM's bytes are those of the ``roam``
mode on the same run (36 B per node of each full tree it sends).

    python benchmarks/map_consensus.py --json [--robots 3] [--seed 0] [--comm-range 10] [--drop 0.2]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from kimera_multi_py.comms.comm_range import neighbours_within
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.eval.map_metrics import TeamMapReport, phi, team_map_report
from kimera_multi_py.eval.slam import map_quality
from kimera_multi_py.mapping.config import MappingConfig, get_submap_map
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.consensus import MapConsensus, MapConsensusParams
from kimera_multi_py.mapshare.exchange import MapExchange
from kimera_multi_py.mapshare.fusion import centralised_team_map, octree_cells
from kimera_multi_py.sim.scenario import load_scenario
from kimera_multi_py.sim.simulation import Simulation

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default=str(ROOT / "sims" / "office.toml"))
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modes", default="roam,exact,laplacian")
    ap.add_argument("--period", type=float, default=1.0, help="exchange period (s of simulated time)")
    ap.add_argument("--laplacian-period", type=float, default=5.0,
                    help="laplacian's period (its float states are large; 1 s costs ~5x the bytes and time)")
    ap.add_argument("--tail", type=float, default=30.0, help="seconds of exchange after the last keyframe")
    ap.add_argument("--comm-range", type=float, default=None)
    ap.add_argument("--drop", type=float, default=0.0)
    ap.add_argument("--reorder", action="store_true", help="shuffle each round's deliveries (arrival order)")
    ap.add_argument("--phi-every", type=int, default=5, help="rounds between phi samples")
    ap.add_argument("--max-keyframes", type=int, default=None, help="per robot (for quick runs)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    cfg = load_scenario(args.scenario, robots=args.robots)
    sim = Simulation(cfg, args.seed)
    mcfg = MappingConfig()
    robots = list(range(sim.num_robots))
    maps: dict[int, SubmapMap] = {r: get_submap_map(mcfg) for r in robots}
    modes = [m for m in args.modes.split(",") if m]
    period = {m: args.laplacian_period if m == "laplacian" else args.period for m in modes}
    nodes = {m: {r: MapConsensus(r, maps[r], MapConsensusParams(mode=m, period=period[m]), team_size=len(robots))
                 for r in robots} for m in modes}
    for team in nodes.values():
        for n in team.values():
            n.set_frame(0)  # true poses: everyone is in the world frame
    position = {r: np.zeros(3) for r in robots}

    def links(now: float) -> dict[int, set[int]]:
        return neighbours_within(position, args.comm_range)

    nets = {m: MapExchange(nodes[m], links=links, drop=args.drop, reorder=args.reorder, seed=args.seed) for m in modes}
    reports = {m: TeamMapReport(m, 0) for m in modes}
    wall = dict.fromkeys(modes, 0.0)
    prior = maps[0].octree.model.prior_row
    rounds = 0

    def exchange(now: float) -> None:
        nonlocal rounds
        rounds += 1
        for m in modes:
            t0 = time.perf_counter()
            nets[m].round(now)
            wall[m] += time.perf_counter() - t0
            if rounds % 50 == 0:
                print(f"round {rounds} {m}: {nets[m].total_bytes()} B, {wall[m]:.0f} s", file=sys.stderr, flush=True)
            if rounds % args.phi_every == 0:
                pairs = sorted({(min(i, j), max(i, j)) for i, js in links(now).items() for j in js})
                reports[m].record_phi(phi({r: n.team_cells() for r, n in nodes[m].items()}, pairs, prior))

    per = mcfg.keyframes_per_submap
    t_map = time.perf_counter()
    t_next, keyframes, last = 0.0, 0, 0.0
    for kf in sim.stream():
        if args.max_keyframes is not None and kf.index >= args.max_keyframes:
            continue
        while kf.stamp >= t_next:
            exchange(t_next)
            t_next += args.period
        m = maps[kf.robot]
        sid = kf.index // per
        if sid not in m.submaps:
            m.new_submap(sid, kf.true_pose)
        hits = kf.scan.points()
        m.integrate(sid, inverse(m.submaps[sid].T) @ kf.true_pose, hits, kf.scan.labels, kf.scan.max_range)
        position[kf.robot] = kf.true_pose[:3, 3]
        keyframes += 1
        last = kf.stamp
    while t_next <= last + args.tail:
        exchange(t_next)
        t_next += args.period
    total_wall = time.perf_counter() - t_map

    # reference, quality and the report
    ref_tree = centralised_team_map(maps)
    ref = octree_cells(ref_tree)
    lo, hi = ref_tree.model.lo, ref_tree.model.hi
    grid = sim.world.gt_voxel_grid(mcfg.octree.resolution)
    centers, gt = grid.centers().reshape(-1, 3), grid.labels.reshape(-1)
    roam_ref = {r: nodes["roam"][r].roam_bytes for r in robots} if "roam" in nodes else None
    out: dict[str, object] = {
        "scenario": cfg.name, "robots": len(robots), "seed": args.seed, "keyframes": keyframes,
        "period_s": period, "tail_s": args.tail, "comm_range": args.comm_range, "drop": args.drop,
        "reorder": args.reorder,
        "rounds": rounds, "wall_s": round(total_wall, 1), "centralised_cells": int(len(ref[0])),
        "centralised_quality": map_quality(ref_tree, np.eye(4), centers, gt),
        "single_robot_quality": {str(r): map_quality(maps[r].octree, np.eye(4), centers, gt) for r in robots},
    }
    for m in modes:
        team = nodes[m]
        rep = team_map_report(
            m, rounds, {r: n.team_cells() for r, n in team.items()}, ref, (lo, hi),
            {r: dict(nets[m].bytes[r]) for r in robots}, roam_ref or {r: n.roam_bytes for r, n in team.items()},
            reports[m])
        d = rep.to_dict()
        d["roam_bytes_alongside"] = {str(r): n.roam_bytes for r, n in team.items()}
        d["bytes_total"] = nets[m].total_bytes()
        d["team_map"] = {str(r): map_quality(n.team_map, np.eye(4), centers, gt) for r, n in team.items()}
        d["wall_s"] = round(wall[m], 1)
        d["dropped"] = nets[m].dropped
        n_phi = len(d["phi"])  # type: ignore[arg-type]
        d["phi"] = {"every_rounds": args.phi_every, "first": d["phi"][:3], "last": d["phi"][-3:], "samples": n_phi}  # type: ignore[index]
        d["phi_per_cell"] = d["phi_per_cell"][-3:]  # type: ignore[index]
        d["phi_roam"] = d["phi_roam"][-3:]  # type: ignore[index]
        out[m] = d
    print(json.dumps(out, indent=None if args.json else 2, default=float))


if __name__ == "__main__":
    main()
