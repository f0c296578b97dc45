"""TeamMaps: the figures of team_map_quality per set of poses, whether built here or in worker processes."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.eval.accuracy import ScanRecord, TeamMaps, team_map_quality
from kimera_multi_py.mapping.config import MappingConfig, get_octree


def _pose(rng: np.random.Generator, x: float, y: float) -> np.ndarray:
    a = rng.uniform(-np.pi, np.pi)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = [x, y, 1.0]
    return T


def _team(rng: np.random.Generator, robots: int = 2, frames: int = 6) -> tuple[list[list[ScanRecord]],
                                                                                list[np.ndarray]]:
    scans, poses = [], []
    for _ in range(robots):
        scans.append([ScanRecord(np.c_[rng.uniform(-4, 4, (300, 2)), rng.uniform(-1, 1.5, 300)].astype(np.float32),
                                 rng.integers(1, 13, 300), 5.0) for _ in range(frames)])
        poses.append(np.stack([_pose(rng, *rng.uniform(0, 3, 2)) for _ in range(frames)]))
    return scans, poses


def _grid(mapping: MappingConfig, scans: list[list[ScanRecord]], poses: list[np.ndarray]) -> tuple[np.ndarray,
                                                                                                      np.ndarray]:
    """Cells around the scans, labelled by a map built at the true poses (so the figures are not trivial)."""
    r = mapping.octree.resolution
    g = np.arange(-5, 8, 2 * r)
    centers = np.stack(np.meshgrid(g, g, np.arange(-0.5, 2.5, 2 * r), indexing="ij"), -1).reshape(-1, 3)
    tree = get_octree(mapping.octree)
    for rs, rp in zip(scans, poses, strict=True):
        for s, T in zip(rs, rp, strict=True):
            tree.insert_scan(T[:3, 3], transform_points(T, s.points), s.labels, s.max_range)
    return centers, tree.class_at(centers)


def _built(mapping: MappingConfig, scans: list[list[ScanRecord]], poses: dict[str, list[np.ndarray]],
           centers: np.ndarray, gt: np.ndarray, workers: int, here: set[str]) -> dict[str, dict[str, float]]:
    maps = TeamMaps(mapping, scans, centers, gt, workers=workers)
    for name, p in poses.items():
        maps.start(name, p, here=name in here)
    return maps.result()


def test_team_maps_equal_team_map_quality_in_process_and_in_workers() -> None:
    rng = np.random.default_rng(3)
    mapping = MappingConfig()
    scans, truth = _team(rng)
    centers, gt = _grid(mapping, scans, truth)
    noisy = [p.copy() for p in truth]
    for p in noisy:
        p[:, :3, 3] += rng.normal(0, 0.3, (len(p), 3))
    drift = [p @ _pose(rng, 0.5, 0.2) for p in truth]
    poses = {"true_poses": truth, "noisy": noisy, "drift": drift}
    want = {name: team_map_quality(mapping, scans, p, centers, gt) for name, p in poses.items()}
    assert want["true_poses"] == {"occupancy_f1": 1.0, "semantic_miou": 1.0}
    assert want["noisy"]["semantic_miou"] < 1.0  # the cases do differ
    assert _built(mapping, scans, poses, centers, gt, workers=0, here=set()) == want
    for workers, here in ((1, {"drift"}), (2, set())):
        got = _built(mapping, scans, poses, centers, gt, workers=workers, here=here)
        assert got == want
        assert list(got) == list(poses)
