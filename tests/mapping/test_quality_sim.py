"""Map and object quality on the simulator's default office (3 robots, 10 % label noise).

Every keyframe of every robot is integrated at its ground-truth pose with the default mapping
configuration; the figures are scored against the simulator's ground truth. The whole run is
built once per module (about 15 s).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.core.geometry import transform_points
from kimera_multi_py.core.semantics import CLASS_IDS, CLASS_NAMES
from kimera_multi_py.eval.metrics import (
    object_precision_recall,
    occupancy_precision_recall,
    semantic_iou_per_class,
    semantic_miou,
)
from kimera_multi_py.mapping import ObjectMap, SemanticOctree
from kimera_multi_py.mapping.config import get_object_map, get_octree, mapping_config
from kimera_multi_py.sim import Simulation, load_scenario

OFFICE = Path(__file__).resolve().parents[2] / "sims" / "office.toml"
HUMAN = CLASS_IDS["human"]
pytestmark = pytest.mark.slow  # the office run below


@dataclass
class OfficeRun:
    sim: Simulation
    tree: SemanticOctree
    objects: ObjectMap
    pred: np.ndarray  # map label per ground-truth cell (-1 unknown)
    gt: np.ndarray  # ground-truth label per cell
    object_seen: np.ndarray  # per ground-truth object: keyframes with >= 8 true hits on it
    human_hits: int  # true end points on walking humans


def _hits_per_object(sim: Simulation, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """True end points inside each ground-truth object's (slightly grown) box."""
    objs = sim.world.objects
    keep = np.isin(labels, [o.label for o in objs])
    points, labels = points[keep], labels[keep]
    c = np.array([o.centroid for o in objs])
    half = np.array([o.size for o in objs]) / 2 + 0.03
    cy, sy = np.cos([o.yaw for o in objs]), np.sin([o.yaw for o in objs])
    d = points[:, None, :] - c[None]
    local = np.stack(
        [d[..., 0] * cy + d[..., 1] * sy, -d[..., 0] * sy + d[..., 1] * cy, d[..., 2]], -1
    )
    inside = np.all(np.abs(local) <= half[None], axis=2)
    inside &= labels[:, None] == np.array([o.label for o in objs])[None]
    return inside.sum(axis=0)


@pytest.fixture(scope="module")
def office() -> OfficeRun:
    cfg = load_scenario(OFFICE, env=False)
    assert cfg.sensor.label_flip == pytest.approx(0.1) and cfg.humans, "not the default office"
    sim = Simulation(cfg, seed=0)
    mcfg = mapping_config()
    assert mcfg.octree.resolution == pytest.approx(0.1)
    tree, objects = get_octree(mcfg.octree), get_object_map(mcfg)
    seen = np.zeros(len(sim.world.objects), dtype=int)
    human_hits = 0
    for k, kf in enumerate(sim.stream()):
        T, scan = kf.true_pose, kf.scan
        pts = transform_points(T, scan.points())
        tree.insert_scan(T[:3, 3], pts, scan.labels, scan.max_range)
        objects.update(pts[scan.hit], scan.labels[scan.hit], stamp=k)
        truth = kf.true_scan
        tp = transform_points(T, truth.points()[truth.hit])
        seen += _hits_per_object(sim, tp, truth.labels[truth.hit]) >= 8
        human_hits += int(np.sum(truth.labels == HUMAN))
    objects.merge_fragments(tree, mcfg.objects.fragment_gap)
    grid = sim.world.gt_voxel_grid(0.1)
    pred = tree.class_at(grid.centers().reshape(-1, 3))
    return OfficeRun(
        sim, tree, objects, pred, grid.labels.reshape(-1).astype(np.int64), seen, human_hits
    )


def test_occupancy_f1(office: OfficeRun) -> None:
    s = occupancy_precision_recall(office.pred, office.gt)
    assert s["cells"] > 300_000  # the observed part of the office is scored, not a corner
    print(f"occupancy precision {s['precision']:.4f} recall {s['recall']:.4f} F1 {s['f1']:.4f}")
    assert s["f1"] >= 0.90


def test_semantic_miou(office: OfficeRun) -> None:
    per = semantic_iou_per_class(office.pred, office.gt)
    assert set(per) == set(range(1, len(CLASS_NAMES) - 1))  # every static class is present
    miou = semantic_miou(office.pred, office.gt)
    print("IoU", {CLASS_NAMES[c]: round(v, 3) for c, v in per.items()}, f"mIoU {miou:.4f}")
    assert miou >= 0.80


def test_walking_humans_leave_no_cells(office: OfficeRun) -> None:
    assert office.human_hits > 500  # the person in the corridor was seen, many times
    assert not np.any(np.argmax(office.tree.values, axis=1) == HUMAN)
    assert not np.any(office.pred == HUMAN)


def test_objects_precision_recall(office: OfficeRun) -> None:
    objs = office.sim.world.objects
    observed = office.object_seen >= office.objects.confirm_after
    assert observed.sum() >= 0.9 * len(objs)
    conf = office.objects.confirmed()
    s = object_precision_recall(
        np.array([lm.label for lm in conf]),
        np.array([lm.position for lm in conf]),
        np.array([o.label for o in objs])[observed],
        np.array([o.centroid for o in objs])[observed],
        max_distance=0.5,
    )
    print({k: round(v, 3) for k, v in s.items()})
    assert s["precision"] >= 0.9 and s["recall"] >= 0.9
    assert s["mean_error"] <= 0.15
