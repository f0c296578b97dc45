"""g2o and TORO pose graphs, single- or multi-robot: SE(3) (``VERTEX_SE3:QUAT`` /
``EDGE_SE3:QUAT``, TORO ``VERTEX3`` / ``EDGE3``) and SE(2) (``VERTEX_SE2`` / ``EDGE_SE2``, as
planar SE(3)).

Multi-robot files use gtsam ``Symbol`` keys (``chr << 56 | index``, Kimera-RPGO's convention):
the letter names the robot (``'a'`` is robot 0). Plain integer ids belong to robot 0; split them
among robots with :func:`kimera_multi_py.core.posegraph.split_contiguous`.

The g2o information matrix is ordered ``[translation, rotation]``; it is stored here in gtsam's
``[rotation, translation]`` order, which is what ``gtsam.readG2o`` does too.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from kimera_multi_py.core.errors import DatasetError
from kimera_multi_py.core.geometry import make_pose, quat_to_rot, rot_to_quat
from kimera_multi_py.core.ids import MAX_AGENT_ID
from kimera_multi_py.core.posegraph import PoseGraph, chain_odometry, split_key
from kimera_multi_py.io.planar import (
    information_from_se2,
    information_to_se2,
    pose_to_se2,
    se2_to_pose,
)
from kimera_multi_py.io.text import read_text

log = logging.getLogger(__name__)

_PERM = np.array([3, 4, 5, 0, 1, 2])  # g2o [t, R] <-> gtsam [R, t]
_TRIU = np.triu_indices(6)
_SYMBOL_MIN = 1 << 56


def _numbers(path: Path, lineno: int, fields: list[str], count: int, tag: str) -> np.ndarray:
    if len(fields) != count:
        raise DatasetError(f"{path}:{lineno}: {tag} needs {count} values, got {len(fields)}")
    try:
        vals = np.array([float(f) for f in fields])
    except ValueError:
        raise DatasetError(f"{path}:{lineno}: non-numeric value in {tag}") from None
    if not np.all(np.isfinite(vals)):
        raise DatasetError(f"{path}:{lineno}: non-finite value in {tag}")
    return vals


def _pose_id(path: Path, lineno: int, token: str) -> int:
    try:
        value = int(token)
    except ValueError:
        raise DatasetError(f"{path}:{lineno}: pose id {token!r} is not an integer") from None
    if value < 0:
        raise DatasetError(f"{path}:{lineno}: negative pose id {value}")
    return value


def _pose_from(path: Path, lineno: int, vals: np.ndarray) -> np.ndarray:
    q = vals[3:7]
    norm = np.linalg.norm(q)
    if not 0.5 < norm < 2.0:
        raise DatasetError(f"{path}:{lineno}: quaternion norm {norm:.3g} is not ~1")
    return make_pose(quat_to_rot(q / norm), vals[:3])


def information_from_g2o(upper: np.ndarray) -> np.ndarray:
    """21 upper-triangular g2o values ``[t, R]`` -> 6x6 information in gtsam order."""
    full = np.zeros((6, 6))
    full[_TRIU] = upper
    full = full + np.triu(full, 1).T
    return full[np.ix_(_PERM, _PERM)]


def information_to_g2o(info: np.ndarray) -> np.ndarray:
    """6x6 gtsam-order information -> 21 g2o upper-triangular values."""
    inv = np.argsort(_PERM)
    return np.asarray(info)[np.ix_(inv, inv)][_TRIU]


def _gtsam_information(path: Path, lineno: int, info: np.ndarray) -> np.ndarray:
    """The information gtsam actually uses for an indefinite matrix (``R'R`` of its factor)."""
    import gtsam

    if np.any(np.diag(info) <= 0.0):
        raise DatasetError(f"{path}:{lineno}: information matrix has a non-positive diagonal")
    R = gtsam.noiseModel.Gaussian.Information(info).R()
    fixed = R.T @ R
    if not np.all(np.isfinite(fixed)):
        raise DatasetError(f"{path}:{lineno}: gtsam cannot factor the information matrix")
    return 0.5 * (fixed + fixed.T)


# tag -> (vertex?, 2-D?, numbers after the ids)
_TAGS = {
    "VERTEX_SE3:QUAT": (True, False, 7), "EDGE_SE3:QUAT": (False, False, 28),
    "VERTEX3": (True, False, 6), "EDGE3": (False, False, 27),
    "VERTEX_SE2": (True, True, 3), "EDGE_SE2": (False, True, 9),
}
_IGNORED = ("FIX", "PARAMS_SE3OFFSET")


def rpy_to_rot(rpy: np.ndarray) -> np.ndarray:
    """TORO's ``roll, pitch, yaw`` -> ``Rz(yaw) Ry(pitch) Rx(roll)`` (gtsam's ``Rot3.Ypr``)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _vertex_pose(path: Path, lineno: int, tag: str, vals: np.ndarray) -> np.ndarray:
    if tag == "VERTEX_SE3:QUAT":
        return _pose_from(path, lineno, vals)
    if tag == "VERTEX3":
        return make_pose(rpy_to_rot(vals[3:6]), vals[:3])
    return se2_to_pose(vals)


def _edge(path: Path, lineno: int, tag: str, vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Measurement and gtsam-order information of one edge line."""
    if tag == "EDGE_SE3:QUAT":
        return _pose_from(path, lineno, vals[:7]), information_from_g2o(vals[7:])
    if tag == "EDGE3":
        # TORO: x y z roll pitch yaw, information over the same order ([t, R], as g2o's)
        return make_pose(rpy_to_rot(vals[3:6]), vals[:3]), information_from_g2o(vals[6:])
    return se2_to_pose(vals[:3]), information_from_se2(vals[3:])


def read_g2o(path: str | Path) -> PoseGraph:
    """Read a g2o / TORO pose graph. Raises :class:`DatasetError` naming file and line on bad
    input (binary or undecodable files included).

    3-D: ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` (g2o) and ``VERTEX3`` / ``EDGE3`` (TORO,
    ``x y z roll pitch yaw`` and 21 information values in the same ``[t, R]`` order). 2-D:
    ``VERTEX_SE2`` / ``EDGE_SE2``, lifted to planar SE(3) (:mod:`.planar`; ``graph.planar``).
    A file with edges but no vertices (gtsam's ``sphere2500.txt``) is initialised by chaining
    each robot's odometry. Symbol keys (>= 2**56) give the owning robot; otherwise every pose
    belongs to robot 0. Pose ids may have gaps: ``local`` is the rank of the id within its robot.
    """
    path = Path(path)
    text = read_text(path, "g2o file")
    vertex_ids: list[int] = []
    vertex_poses: list[np.ndarray] = []
    vertex_line: dict[int, int] = {}
    edges: list[tuple[int, int, int, str, np.ndarray]] = []
    dims: dict[bool, int] = {}  # 2-D? -> first line
    for lineno, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        tag = fields[0]
        if tag in _IGNORED:
            log.debug("%s:%d: ignoring %s", path, lineno, tag)
            continue
        if tag not in _TAGS:
            kind = "landmark" if tag.startswith(("VERTEX_XY", "EDGE_SE2_XY", "EDGE_SE3_XYZ",
                                                 "VERTEX_TRACKXYZ", "EDGE_SE3_TRACKXYZ")) else "g2o"
            raise DatasetError(f"{path}:{lineno}: unknown {kind} tag {tag!r} (pose graphs only: "
                               + ", ".join(_TAGS) + ")")
        is_vertex, planar, count = _TAGS[tag]
        dims.setdefault(planar, lineno)
        if len(dims) > 1:
            raise DatasetError(f"{path}:{lineno}: {tag} mixes 2-D and 3-D tags (line "
                               f"{dims[not planar]} is {'2' if not planar else '3'}-D)")
        if is_vertex:
            if len(fields) < 2:
                raise DatasetError(f"{path}:{lineno}: {tag} without an id")
            vid = _pose_id(path, lineno, fields[1])
            if vid in vertex_line:
                raise DatasetError(
                    f"{path}:{lineno}: duplicate vertex {vid} (first on line {vertex_line[vid]})"
                )
            vals = _numbers(path, lineno, fields[2:], count, tag)
            vertex_line[vid] = lineno
            vertex_ids.append(vid)
            vertex_poses.append(_vertex_pose(path, lineno, tag, vals))
        else:
            if len(fields) < 3:
                raise DatasetError(f"{path}:{lineno}: {tag} without two pose ids")
            a, b = _pose_id(path, lineno, fields[1]), _pose_id(path, lineno, fields[2])
            if a == b:
                raise DatasetError(f"{path}:{lineno}: edge from pose {a} to itself")
            edges.append((lineno, a, b, tag, _numbers(path, lineno, fields[3:], count, tag)))
    planar = bool(dims and next(iter(dims)))
    chained = not vertex_ids
    if chained:
        if not edges:
            raise DatasetError(f"{path}: no vertices and no edges (" + ", ".join(_TAGS) + ")")
        vertex_ids = sorted({v for _, a, b, _, _ in edges for v in (a, b)})
        vertex_line = {v: next(n for n, a, b, _, _ in edges if v in (a, b)) for v in vertex_ids}
        log.info("%s: no vertices; initial values chain the odometry", path)
    else:
        for lineno, a, b, _, _ in edges:
            for v in (a, b):
                if v not in vertex_line:
                    raise DatasetError(
                        f"{path}:{lineno}: edge refers to pose {v}, which has no vertex")

    ids = np.array(vertex_ids, dtype=np.int64)
    robot, local = _owners(path, ids, vertex_ids, vertex_line)
    index = {vid: k for k, vid in enumerate(vertex_ids)}
    m = len(edges)
    edge_i = np.zeros(m, dtype=int)
    edge_j = np.zeros(m, dtype=int)
    meas = np.zeros((m, 4, 4))
    info = np.zeros((m, 6, 6))
    indefinite = 0
    for e, (lineno, a, b, tag, vals) in enumerate(edges):
        edge_i[e], edge_j[e] = index[a], index[b]
        meas[e], info[e] = _edge(path, lineno, tag, vals)
        if np.linalg.eigvalsh(info[e])[0] <= 0.0:
            info[e] = _gtsam_information(path, lineno, info[e])
            indefinite += 1
    if indefinite:
        log.warning("%s: %d information matrices are not positive definite; using gtsam's "
                    "careful Cholesky factor R'R as gtsam.readG2o does", path, indefinite)
    _check_odometry(path, robot, local, edge_i, edge_j)
    if chained:
        order = np.lexsort((local, robot))  # chain_odometry wants each robot consecutive
        rank = np.empty_like(order)
        rank[order] = np.arange(len(order))
        poses = chain_odometry(str(path), robot[order], rank[edge_i], rank[edge_j], meas)[rank]
    else:
        poses = np.stack(vertex_poses)
    return PoseGraph(poses=poses, robot=robot, local=local, ids=ids, edge_i=edge_i,
                     edge_j=edge_j, measurement=meas, information=info, source=path.name,
                     planar=planar)


def _owners(path: Path, ids: np.ndarray, vertex_ids: list[int],
            vertex_line: dict[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``robot`` (from Symbol keys, else 0) and ``local`` (rank of the id within its robot)."""
    symbolic = ids >= _SYMBOL_MIN
    if symbolic.any() and not symbolic.all():
        first = int(np.flatnonzero(symbolic != symbolic[0])[0])
        raise DatasetError(
            f"{path}:{vertex_line[vertex_ids[first]]}: mixes gtsam Symbol keys and plain ids"
        )
    robot = np.zeros(len(ids), dtype=int)
    if symbolic.all():
        for k, vid in enumerate(vertex_ids):
            r, _ = split_key(vid)
            if not 0 <= r <= MAX_AGENT_ID:
                raise DatasetError(
                    f"{path}:{vertex_line[vid]}: Symbol key {vid} does not use a letter a..z"
                )
            robot[k] = r
    local = np.zeros(len(ids), dtype=int)
    for r in np.unique(robot):
        idx = np.flatnonzero(robot == r)
        idx = idx[np.argsort(ids[idx], kind="stable")]
        local[idx] = np.arange(len(idx))
        span = int(ids[idx[-1]] - ids[idx[0]]) + 1
        if span != len(idx):
            log.warning("%s: robot %d pose ids have %d gaps; poses are renumbered by rank",
                        path, r, span - len(idx))
    return robot, local


def _check_odometry(path: Path, robot: np.ndarray, local: np.ndarray,
                    edge_i: np.ndarray, edge_j: np.ndarray) -> None:
    """Log (do not fail on) odometry chains that are broken or run backwards."""
    same = robot[edge_i] == robot[edge_j]
    step = local[edge_j] - local[edge_i]
    backwards = int(np.count_nonzero(same & (step == -1)))
    if backwards:
        log.info("%s: %d odometry edges run backwards (j -> j-1); kept as given", path, backwards)
    for r in np.unique(robot):
        n_r = int(np.count_nonzero(robot == r))
        sel = same & (robot[edge_i] == r) & (np.abs(step) == 1)
        linked = np.unique(np.minimum(local[edge_i[sel]], local[edge_j[sel]]))
        if len(linked) < n_r - 1:
            log.warning("%s: robot %d odometry chain has %d breaks", path, r, n_r - 1 - len(linked))


def write_g2o(path: str | Path, graph: PoseGraph, poses: np.ndarray | None = None) -> None:
    """Write ``graph`` (with ``poses`` in place of its initial values) using its source ids;
    a planar graph (read from a 2-D file) is written as ``VERTEX_SE2`` / ``EDGE_SE2``."""
    poses = graph.poses if poses is None else np.asarray(poses, dtype=float)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ids = graph.ids.astype(np.int64)
    lines = []
    if graph.planar:
        xyt, zt = pose_to_se2(poses), pose_to_se2(graph.measurement)
        for k in range(graph.num_poses):
            lines.append(f"VERTEX_SE2 {int(ids[k])} " + " ".join(f"{v:.9g}" for v in xyt[k]))
        for e in range(graph.num_edges):
            vals = (*zt[e], *information_to_se2(graph.information[e]))
            lines.append(f"EDGE_SE2 {int(ids[graph.edge_i[e]])} {int(ids[graph.edge_j[e]])} "
                         + " ".join(f"{v:.9g}" for v in vals))
        path.write_text("\n".join(lines) + "\n")
        return
    q = rot_to_quat(poses[:, :3, :3])
    qm = rot_to_quat(graph.measurement[:, :3, :3])
    for k in range(graph.num_poses):
        t = poses[k, :3, 3]
        lines.append(
            f"VERTEX_SE3:QUAT {int(ids[k])} "
            + " ".join(f"{v:.9g}" for v in (*t, *q[k]))
        )
    for e in range(graph.num_edges):
        vals = (*graph.measurement[e, :3, 3], *qm[e], *information_to_g2o(graph.information[e]))
        lines.append(
            f"EDGE_SE3:QUAT {int(ids[graph.edge_i[e]])} {int(ids[graph.edge_j[e]])} "
            + " ".join(f"{v:.9g}" for v in vals)
        )
    path.write_text("\n".join(lines) + "\n")
