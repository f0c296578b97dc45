"""Scan insertion throughput of the semantic octree against C++ OctoMap, in the same run.

Builds dense range-category scans (120 x 168 = 20,160 rays) from keyframes of the default
office scenario and inserts the *same* world-frame points into

* ``pyoctomap.OcTree(res).insertPointCloud(points, origin, max_range)`` -- C++ OctoMap,
  binary occupancy (the reference), and
* ``SemanticOctree(res, K)`` with OctoMap's scan semantics (no free margin, no surface
  offset) and K semantic classes, i.e. K + 1 log-odds per cell.

Rays without a return are placed just beyond ``max_range``, so both maps clear free space up
to ``max_range`` and mark nothing occupied for them. Each map is built ``--repeats`` times
from scratch, alternating, and the fastest build of each counts. The simulator's 12 labels are
folded onto ``--num-classes`` classes ((label - 1) mod K + 1) when K is smaller.

    python benchmarks/octree_insert.py --json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.semantics import NUM_CLASSES
from kimera_multi_py.mapping import SemanticOctree
from kimera_multi_py.sim import Simulation, load_scenario

REPO = Path(__file__).resolve().parents[1]


def make_scans(
    scenario: str, scans: int, rows: int, cols: int, num_classes: int, seed: int = 0
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``(origin, world points, labels)`` for ``scans`` keyframes spread over the robots."""
    cfg = load_scenario(scenario, env=False)
    cfg = cfg.model_copy(
        update={"sensor": cfg.sensor.model_copy(update={"rows": rows, "cols": cols})}
    )
    sim = Simulation(cfg, seed=seed)
    total = sim.num_keyframes
    every = max(1, total // scans)
    out = []
    for i, kf in enumerate(sim.stream()):
        if i % every or len(out) == scans:
            continue
        s = kf.scan
        ranges = np.where(s.hit, s.ranges, 1.05 * s.max_range)
        pts = transform_points(kf.true_pose, s.directions * ranges[:, None])
        labels = np.where(s.labels > 0, (s.labels.astype(np.int64) - 1) % num_classes + 1, 0)
        out.append((kf.true_pose[:3, 3].copy(), np.ascontiguousarray(pts), labels))
    return out


def build_ours(
    scans: list, resolution: float, num_classes: int, max_range: float
) -> tuple[float, SemanticOctree]:
    tree = SemanticOctree(resolution, num_classes)
    t0 = time.perf_counter()
    for origin, pts, labels in scans:
        tree.insert_scan(origin, pts, labels, max_range)
    return time.perf_counter() - t0, tree


def build_octomap(scans: list, resolution: float, max_range: float) -> tuple[float, object]:
    import pyoctomap

    tree = pyoctomap.OcTree(resolution)
    t0 = time.perf_counter()
    for origin, pts, _ in scans:
        tree.insertPointCloud(pts, origin, max_range)
    return time.perf_counter() - t0, tree


def agreement(ours: SemanticOctree, octomap: object, samples: int, seed: int = 0) -> float:
    """Fraction of sampled leaves of ours whose centre OctoMap classifies the same way."""
    rng = np.random.default_rng(seed)
    idx = rng.choice(ours.num_leaves, min(samples, ours.num_leaves), replace=False)
    centers = ours.leaves().centers[idx]
    occ = ours.occupied_leaves()[idx]
    same = 0
    for c, o in zip(centers, occ, strict=True):
        node = octomap.search(c)  # type: ignore[attr-defined]
        if node is not None:
            same += int(bool(octomap.isNodeOccupied(node)) == bool(o))  # type: ignore[attr-defined]
    return same / len(idx)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON only")
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--scans", type=int, default=24)
    ap.add_argument("--rows", type=int, default=120)
    ap.add_argument("--cols", type=int, default=168)
    ap.add_argument("--resolution", type=float, default=0.1)
    ap.add_argument("--num-classes", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    scans = make_scans(args.scenario, args.scans, args.rows, args.cols, args.num_classes)
    max_range = float(load_scenario(args.scenario, env=False).sensor.max_range)
    points = sum(len(p) for _, p, _ in scans)
    ours_t, ref_t = [], []
    for _ in range(args.repeats):
        t, octomap = build_octomap(scans, args.resolution, max_range)
        ref_t.append(t)
        t, ours = build_ours(scans, args.resolution, args.num_classes, max_range)
        ours_t.append(t)
    lengths = np.concatenate([np.linalg.norm(p - o, axis=1) for o, p, _ in scans])
    results = {
        "scenario": Path(args.scenario).stem,
        "scans": len(scans),
        "rays_per_scan": args.rows * args.cols,
        "resolution": args.resolution,
        "num_classes": args.num_classes,
        "logodds_per_cell": args.num_classes + 1,
        "labels_folded": args.num_classes < NUM_CLASSES,
        "mean_ray_length_m": round(float(np.minimum(lengths, max_range).mean()), 3),
        "points_per_s": round(points / min(ours_t)),
        "octomap_points_per_s": round(points / min(ref_t)),
        "ratio": round(min(ref_t) / min(ours_t), 3),
        "seconds": [round(t, 3) for t in ours_t],
        "octomap_seconds": [round(t, 3) for t in ref_t],
        "leaves": ours.num_leaves,
        "octomap_leaves": int(octomap.getNumLeafNodes()),  # type: ignore[attr-defined]
        "nodes": ours.num_nodes,
        "octomap_nodes": int(octomap.size()),  # type: ignore[attr-defined]
        "bytes": ours.nbytes,
        "octomap_bytes": int(octomap.memoryUsage()),  # type: ignore[attr-defined]
        "occupancy_agreement": round(agreement(ours, octomap, 3000), 4),
    }
    print(json.dumps(results) if args.json else json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
