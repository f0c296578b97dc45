"""The walls' axes, and object boxes aligned with them."""

import numpy as np
import pytest

from kimera_multi_py.core.geometry import make_pose, so3_exp, transform_points
from kimera_multi_py.mapping import ObjectMap
from kimera_multi_py.mapping.axes import StructureAxes

from .helpers import FLOOR, TABLE, WALL, K
from .test_objects import OBJECT_CLASSES


def rot(yaw: float) -> np.ndarray:
    return make_pose(so3_exp(np.array([0.0, 0.0, yaw])), np.zeros(3))


def room(yaw: float, rng: np.random.Generator, size=(6.0, 4.0), spacing=0.08, noise=0.02):
    """Wall and floor points of a room turned by ``yaw`` about the origin."""
    sx, sy = size
    u = np.arange(0.0, 1.0, spacing / max(sx, sy))
    z = np.arange(0.0, 2.5, spacing)
    walls = []
    for (x0, y0), (x1, y1) in (((0, 0), (sx, 0)), ((sx, 0), (sx, sy)), ((sx, sy), (0, sy)), ((0, sy), (0, 0))):
        xy = np.array([x0, y0]) + u[:, None] * np.array([x1 - x0, y1 - y0])
        walls.append(np.column_stack([np.repeat(xy, len(z), 0), np.tile(z, len(xy))]))
    W = np.concatenate(walls)
    F = np.column_stack([rng.uniform(0, sx, 800), rng.uniform(0, sy, 800), np.zeros(800)])
    P = np.concatenate([W, F]) + rng.normal(0, noise, (len(W) + len(F), 3))
    return transform_points(rot(yaw), P), np.r_[np.full(len(W), WALL), np.full(len(F), FLOOR)]


def two_faces(center, size, yaw, rng, n=300):
    """Points on two adjacent sides of an upright box turned by ``yaw``: the L a robot sees from
    one corner of a tall object."""
    h = np.asarray(size, float) / 2
    a = np.column_stack([np.full(n, -h[0]), rng.uniform(-h[1], h[1], n), rng.uniform(-h[2], h[2], n)])
    b = np.column_stack([rng.uniform(-h[0], h[0], n), np.full(n, -h[1]), rng.uniform(-h[2], h[2], n)])
    return transform_points(make_pose(so3_exp(np.array([0.0, 0.0, yaw])), np.asarray(center, float)),
                            np.concatenate([a, b]))


@pytest.mark.parametrize("yaw", [0.0, 0.35, -0.6, 1.2])
def test_the_axes_are_the_walls_and_follow_their_submap(yaw):
    rng = np.random.default_rng(1)
    axes = StructureAxes()
    pts, lab = room(yaw, rng)
    axes.add(3, pts[lab == WALL], np.eye(4))
    wrap = (yaw + np.pi / 4) % (np.pi / 2) - np.pi / 4
    assert axes.yaw(lambda s: np.eye(4)) == pytest.approx(wrap, abs=np.radians(0.5))
    # the submap turns by 0.2 rad: its walls' axes turn with it
    turned = (yaw + 0.2 + np.pi / 4) % (np.pi / 2) - np.pi / 4
    assert axes.yaw(lambda s: rot(0.2)) == pytest.approx(turned, abs=np.radians(0.5))


def test_no_walls_no_axes():
    rng = np.random.default_rng(2)
    axes = StructureAxes()
    pts, lab = room(0.3, rng)
    axes.add(0, pts[lab == FLOOR], np.eye(4))  # horizontal surfaces do not vote
    assert axes.yaw(lambda s: np.eye(4)) is None
    # points on a sphere: normals everywhere, no dominant direction
    d = rng.normal(size=(3000, 3))
    axes.add(0, 2.0 * d / np.linalg.norm(d, axis=1, keepdims=True), np.eye(4))
    assert axes.yaw(lambda s: np.eye(4)) is None


def test_an_object_seen_from_one_corner_is_boxed_along_the_walls():
    yaw, center, size = 0.5, np.array([3.0, 2.0, 0.9]), np.array([1.2, 0.5, 1.8])
    errors = {}
    for structure in ([], [WALL, FLOOR]):
        rng = np.random.default_rng(3)
        om = ObjectMap(K, OBJECT_CLASSES, resolution=0.05, confirm_after=1, structure_classes=structure)
        for _ in range(4):
            walls, wl = room(yaw, rng)
            table = two_faces(center, size, yaw, rng)  # the table stands square to the walls
            om.update(np.concatenate([walls, table]), np.r_[wl, np.full(len(table), TABLE)])
        (lm,) = om.confirmed()
        errors[bool(structure)] = np.linalg.norm(lm.position - center)
        if structure:
            c, s, R = lm.box()
            assert s == pytest.approx(size + 0.05, abs=0.08)
            assert np.allclose(np.abs(R[:2, :2]), np.abs(rot(yaw)[:2, :2]), atol=0.02)
    assert errors[True] < 0.04
    assert errors[False] > 0.1  # in the map's own axes the L is boxed off-centre


def test_a_frame_that_is_not_upright_has_no_axes():
    rng = np.random.default_rng(4)
    pts, lab = room(0.3, rng)
    tilt = make_pose(so3_exp(np.array([0.5, 0.2, 0.0])), np.zeros(3))
    axes = StructureAxes()
    axes.add(0, transform_points(tilt, pts), np.eye(4))  # mostly oblique normals: no votes
    assert axes.yaw(lambda s: np.eye(4)) is None
    axes.add(0, pts, np.eye(4))
    assert axes.yaw(lambda s: np.eye(4)) == pytest.approx(0.3, abs=np.radians(0.5))
    # the submap later turned out of the upright: its votes no longer give a heading
    assert axes.yaw(lambda s: tilt) is None
