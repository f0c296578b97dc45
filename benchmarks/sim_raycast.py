"""Ray-casting throughput of the simulator, against a reference kernel in the same run.

Casts the default office sensor (48 x 64 rays) and a dense 120 x 180 pattern from the first
keyframes of every robot. The reference is the straightforward kernel: one vectorised slab /
quadric test per primitive, looping over primitives in Python, with no culling.

    python benchmarks/sim_raycast.py --json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.sensors import ray_pattern
from kimera_multi_py.sim.world import BOX, Primitives, cast_rays

REPO = Path(__file__).resolve().parents[1]


def reference_cast(prims: Primitives, origin: np.ndarray, dirs: np.ndarray, max_range: float) -> np.ndarray:
    """Per-primitive loop (vectorised over rays only)."""
    best = np.full(len(dirs), np.inf)
    for m in range(len(prims)):
        o = (origin - prims.center[m]) @ prims.rot[m]
        d = dirs @ prims.rot[m]
        h = prims.half[m]
        if prims.shape[m] == BOX:
            with np.errstate(divide="ignore", invalid="ignore"):
                t1, t2 = (-h - o) / d, (h - o) / d
            tn, tf = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
            t = np.where((tf >= tn) & (tn > 0), tn, np.inf)
        else:
            oe, de = o / h, d / h
            a, b, c = (de * de).sum(1), (oe * de).sum(1), (oe * oe).sum() - 1.0
            disc = b * b - a * c
            with np.errstate(invalid="ignore"):
                t = np.where(disc >= 0, (-b - np.sqrt(disc)) / a, np.inf)
            t = np.where(t > 0, t, np.inf)
        best = np.minimum(best, t)
    return np.where(best <= max_range, best, np.inf)


def bench(sim: Simulation, dirs: np.ndarray, poses: list[np.ndarray], fn, repeats: int) -> tuple[float, list]:
    out = []
    t0 = time.perf_counter()
    for _ in range(repeats):
        out = [fn(sim.world.static, T[:3, 3], dirs @ T[:3, :3].T, 8.0) for T in poses]
    dt = time.perf_counter() - t0
    return repeats * len(poses) * len(dirs) / dt, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON only")
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--keyframes", type=int, default=40)
    args = ap.parse_args()

    sim = Simulation(load_scenario(args.scenario, robots=3), seed=0)
    poses = [p for plan in sim.plans for p in plan.poses[: args.keyframes // 3]]
    s = sim.cfg.sensor
    results = {"scenario": sim.cfg.name, "primitives": len(sim.world.static), "scans": len(poses)}
    for name, (rows, cols) in {"default": (s.rows, s.cols), "dense": (120, 180)}.items():
        dirs = ray_pattern(s.model, s.h_fov_deg, s.v_fov_deg, rows, cols)
        ours, hits = bench(sim, dirs, poses, lambda *a: cast_rays(*a)[0], repeats=3)
        ref, ref_hits = bench(sim, dirs, poses, reference_cast, repeats=1)
        # rays grazing an edge exactly may differ between kernels; everything else must agree
        agree = np.mean(np.concatenate([np.isclose(a, b) for a, b in zip(hits, ref_hits, strict=True)]))
        results[name] = {
            "rays_per_scan": rows * cols,
            "rays_per_s": round(ours),
            "reference_rays_per_s": round(ref),
            "speedup": round(ours / ref, 2),
            "agreeing_rays": float(round(agree, 6)),
        }
    t0 = time.perf_counter()
    n = sum(1 for _ in sim.stream())
    results["simulation_keyframes_per_s"] = round(n / (time.perf_counter() - t0), 1)
    if args.json:
        print(json.dumps(results))
    else:
        print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
