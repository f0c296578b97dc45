"""Scan-to-map odometry: accuracy and cost per keyframe, against dead reckoning in the same run.

Streams one robot of a scenario through :class:`~kimera_multi_py.mapping.scan_odometry.ScanOdometry`
(small_gicp GICP onto the last ``--window`` keyframes' scans, fused with the odometry), once as
the agents run it by default (no floor reference) and once with the floor reference
(:mod:`~kimera_multi_py.mapping.floor`, ``AgentParams.floor_reference``), and reports, for both
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

from kimera_multi_py.eval.metrics import ate_rmse
from kimera_multi_py.geometry import inverse, se3_log
from kimera_multi_py.mapping.floor import FloorReference
from kimera_multi_py.mapping.registration import ScanRegistration
from kimera_multi_py.mapping.scan_odometry import ScanOdometry
from kimera_multi_py.semantics import class_id
from kimera_multi_py.sim import Simulation, load_scenario

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
    o = cfg.odometry
    info = np.diag(np.repeat(1.0 / np.square([np.deg2rad(o.rot_sigma_deg), o.trans_sigma]), 3))
    ref = FloorReference()
    so = ScanOdometry(ScanRegistration(), info, window=window)
    with_floor = ScanOdometry(ScanRegistration(), info, window=window, floor=ref)
    floor = class_id("floor")
    true, dead = [], [np.eye(4)]
    t0 = time.perf_counter()
    for kf, _ in zip(sim.keyframes(robot), range(keyframes), strict=False):
        true.append(kf.true_pose)
        if kf.index:
            dead.append(dead[-1] @ kf.odometry)
        pts, hit = kf.scan.points(), kf.scan.hit
        so.step(kf.index, kf.odometry, pts[hit])
        with_floor.step(kf.index, kf.odometry, pts[hit], pts[hit & (kf.scan.labels == floor)])
    wall = time.perf_counter() - t0
    T = np.array(true)
    n = len(T)
    return {"scenario": cfg.name, "robot": robot, "keyframes": n, "window": window,
            "registration": _chain_figures(T, np.array(so.poses)),
            "registration_with_floor": _chain_figures(T, np.array(with_floor.poses)),
            "dead_reckoning (reference)": _chain_figures(T, np.array(dead)),
            "registration_ms_per_keyframe": 1000 * so.stats.seconds / max(n - 1, 1),
            "stream_ms_per_keyframe (simulator and both chains included)": 1000 * wall / n,
            "counts": {"registered": so.stats.registered, "degenerate": so.stats.degenerate,
                       "gated": so.stats.gated, "failed": so.stats.failed},
            "floor": {"corrected": ref.stats.corrected, "missing": ref.stats.missing, "gated": ref.stats.gated}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--robot", type=int, default=0)
    ap.add_argument("--keyframes", type=int, default=200)
    ap.add_argument("--window", type=int, default=8)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    out = run(args.scenario, args.robot, args.keyframes, args.window)
    print(json.dumps(out, indent=None if args.json else 2))


if __name__ == "__main__":
    main()
