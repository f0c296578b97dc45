"""Closures between views facing apart (docs/algorithms/frontend.md, "Views facing apart").

A camera sees the faces of an object that face it. Two keyframes looking at the same furniture
from opposite sides see opposite faces, so both the objects' centroids and the registration of
the clouds pair a front face with a back face: the closure is off by about the objects' depth
along the view axis, consistently, and PCM keeps such a group. The agent does not join views
whose forward axes are more than ``max_view_angle`` apart.
"""

from dataclasses import replace

import numpy as np

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.closures import Constellation
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.core.geometry import inverse, transform_points, yaw_pose
from kimera_multi_py.core.semantics import class_id

# furniture between the two viewpoints: centre (x, y), size (dx, dy, height), class
BOXES = [((3.0, -1.8), (0.8, 1.4, 0.75), "table"), ((4.2, 0.3), (0.5, 0.5, 0.9), "chair"),
         ((3.4, 1.9), (0.5, 0.5, 0.9), "chair"), ((5.1, -0.6), (0.6, 1.2, 0.9), "cabinet"),
         ((4.6, 2.6), (0.8, 1.6, 0.75), "table"), ((2.6, 0.9), (0.5, 0.5, 0.9), "chair"),
         ((5.6, 1.4), (0.5, 0.5, 0.9), "chair")]
STEP = 0.04


def _face(origin: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    a, b = np.meshgrid(np.arange(0, 1, STEP / np.linalg.norm(u)), np.arange(0, 1, STEP / np.linalg.norm(v)))
    return origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v


def _seen(eye: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """World points of the box faces and side walls that face ``eye``, their labels, and each
    box's centroid of what is seen (as the object map would place it) with its class."""
    pts, labels, xyz, classes = [], [], [], []
    for (cx, cy), (dx, dy, h), cls in BOXES:
        lo = np.array([cx - dx / 2, cy - dy / 2, 0.0])
        faces = [  # (outward normal, origin, u, v)
            ((-1, 0, 0), lo, (0, dy, 0), (0, 0, h)), ((1, 0, 0), lo + (dx, 0, 0), (0, dy, 0), (0, 0, h)),
            ((0, -1, 0), lo, (dx, 0, 0), (0, 0, h)), ((0, 1, 0), lo + (0, dy, 0), (dx, 0, 0), (0, 0, h)),
            ((0, 0, 1), lo + (0, 0, h), (dx, 0, 0), (0, dy, 0))]
        box = []
        for n, o, u, v in faces:
            o, u, v, n = (np.asarray(x, float) for x in (o, u, v, n))
            if n @ (eye - (o + u / 2 + v / 2)) > 0:
                box.append(_face(o, u, v))
        box_pts = np.vstack(box)
        pts.append(box_pts)
        labels.append(np.full(len(box_pts), class_id(cls)))
        xyz.append(box_pts.mean(axis=0))
        classes.append(class_id(cls))
    for y in (-4.0, 4.0):  # side walls along the view axis: they fix y, not x
        wall = _face(np.array([0.0, y, 0.0]), np.array([8.0, 0, 0]), np.array([0, 0, 2.5]))
        pts.append(wall)
        labels.append(np.full(len(wall), class_id("wall")))
    return np.vstack(pts), np.concatenate(labels), np.array(xyz), np.array(classes)


def _constellation(T_world_kf: np.ndarray, keyframe: int) -> Constellation:
    pts, labels, xyz, classes = _seen(T_world_kf[:3, 3])
    to_kf = inverse(T_world_kf)
    return Constellation(keyframe, 0.0, transform_points(to_kf, xyz), classes, np.zeros(1),
                         transform_points(to_kf, pts), labels)


def _closure(params: AgentParams, T_a: np.ndarray, T_b: np.ndarray) -> tuple[np.ndarray | None, Agent]:
    agent = Agent(0, (0, 1), params)
    a, b = _constellation(T_a, 0), _constellation(T_b, 1)
    res = agent._verify(a, b.xyz, b.classes, b.cloud, b.cloud_labels)
    return (None if res is None else res[0]), agent


def _error(Z: np.ndarray, T_a: np.ndarray, T_b: np.ndarray) -> float:
    return float(np.linalg.norm((T_a @ Z)[:3, 3] - T_b[:3, 3]))


def test_views_facing_apart_register_off_by_the_objects_depth_and_are_not_joined():
    T_a = yaw_pose(0.0, 0.2, 0.0, 0.0)  # looking along +x at the furniture
    T_b = yaw_pose(8.0, -0.3, 0.0, np.pi)  # from the far side, looking back
    unlimited = replace(AgentParams(), max_view_angle=np.pi)
    Z, _ = _closure(unlimited, T_a, T_b)
    assert Z is not None  # without the limit the closure is verified and registered ...
    assert _error(Z, T_a, T_b) > 0.2  # ... off by a good part of the furniture's depth
    Z, agent = _closure(AgentParams(), T_a, T_b)
    assert Z is None
    assert agent.stats.rejected_view_angle == 1 and agent.stats.rejected_verification == 1


def test_views_facing_alike_are_joined_accurately():
    T_a = yaw_pose(0.0, 0.2, 0.0, 0.0)
    T_b = yaw_pose(0.9, -0.4, 0.0, np.deg2rad(35.0))
    Z, agent = _closure(AgentParams(), T_a, T_b)
    assert Z is not None and agent.stats.rejected_view_angle == 0
    assert _error(Z, T_a, T_b) < 0.05
