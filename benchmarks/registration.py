"""Scan-to-map odometry: accuracy and cost per keyframe, against dead reckoning in the same run.

Streams one robot of a scenario through :class:`~kimera_multi_py.mapping.scan_odometry.ScanOdometry`
(small_gicp GICP onto the last ``--window`` keyframes' scans, fused with the odometry, with the
agents' correspondence stages), three times: registration alone, with the floor reference
(:mod:`~kimera_multi_py.mapping.floor`), and with the floor and the walls' heading
(:mod:`~kimera_multi_py.mapping.heading`; the agents' default), and reports, for the three
chains and for dead reckoning (the reference), the final
position error per distance travelled and the ATE after anchoring at the true start, plus the
median per-step error against the true relative poses and the registration's milliseconds per
keyframe.

    python benchmarks/registration.py --json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from kimera_multi_py.core.geometry import inverse, se3_log
from kimera_multi_py.core.semantics import class_id
from kimera_multi_py.eval.metrics import ate_rmse
from kimera_multi_py.mapping.floor import FloorReference
from kimera_multi_py.mapping.heading import HeadingReference
from kimera_multi_py.mapping.registration import ScanRegistration
from kimera_multi_py.mapping.scan_odometry import ScanOdometry
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.team.build import agent_params

REPO = Path(__file__).resolve().parents[1]


def _chain_figures(true: np.ndarray, est: np.ndarray) -> dict[str, float]:
    placed = true[0] @ est
    length = float(np.linalg.norm(np.diff(true[:, :3, 3], axis=0), axis=1).sum())
    steps = se3_log(inverse(inverse(true[:-1]) @ true[1:]) @ (inverse(est[:-1]) @ est[1:]))
    return {"drift_per_distance": float(np.linalg.norm(placed[-1, :3, 3] - true[-1, :3, 3]) / length),
            "ate_rmse_m": ate_rmse(placed[:, :3, 3], true[:, :3, 3]),
            "median_step_trans_m": float(np.median(np.linalg.norm(steps[:, 3:], axis=1))),
            "median_step_rot_deg": float(np.degrees(np.median(np.linalg.norm(steps[:, :3], axis=1))))}


def run(scenario: str, robot: int, keyframes: int, window: int, seed: int = 0) -> dict[str, object]:
    cfg = load_scenario(scenario, env=False)
    sim = Simulation(cfg, seed)
    p = agent_params(cfg)
    chains = {name: ScanOdometry(ScanRegistration(p.reg_voxel, p.registration_stages()), p.odom_information(),
                                 window=window, floor=FloorReference() if floor else None,
                                 heading=HeadingReference() if heading else None)
              for name, floor, heading in (("registration", False, False), ("registration_with_floor", True, False),
                                           ("registration_with_floor_and_heading", True, True))}
    floor, wall = class_id("floor"), class_id("wall")
    true, dead = [], [np.eye(4)]
    t0 = time.perf_counter()
    for kf, _ in zip(sim.keyframes(robot), range(keyframes), strict=False):
        true.append(kf.true_pose)
        if kf.index:
            dead.append(dead[-1] @ kf.odometry)
        pts, hit = kf.scan.points(), kf.scan.hit
        for so in chains.values():
            so.step(kf.index, kf.odometry, pts[hit], pts[hit & (kf.scan.labels == floor)],
                    pts[hit & (kf.scan.labels == wall)])
    elapsed = time.perf_counter() - t0
    T = np.array(true)
    n = len(T)
    full = chains["registration_with_floor_and_heading"]
    assert full.floor is not None and full.heading is not None
    return {"scenario": cfg.name, "robot": robot, "seed": seed, "keyframes": n, "window": window,
            **{name: _chain_figures(T, np.array(so.poses)) for name, so in chains.items()},
            "dead_reckoning (reference)": _chain_figures(T, np.array(dead)),
            "registration_ms_per_keyframe": 1000 * chains["registration"].stats.seconds / max(n - 1, 1),
            "stream_ms_per_keyframe (simulator and the three chains included)": 1000 * elapsed / n,
            "counts": {k: getattr(full.stats, k) for k in ("registered", "degenerate", "gated", "failed")},
            "floor": {k: getattr(full.floor.stats, k) for k in ("corrected", "missing", "gated")},
            "heading": {k: getattr(full.heading.stats, k) for k in ("corrected", "missing", "gated")}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--robot", type=int, default=0)
    ap.add_argument("--keyframes", type=int, default=200)
    ap.add_argument("--window", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    out = run(args.scenario, args.robot, args.keyframes, args.window, args.seed)
    print(json.dumps(out, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
