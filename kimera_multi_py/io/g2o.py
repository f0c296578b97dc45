"""g2o SE(3) pose graphs (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``), single- or multi-robot.

Multi-robot files use gtsam ``Symbol`` keys (``chr << 56 | index``, Kimera-RPGO's convention):
the letter names the robot (``'a'`` is robot 0). Plain integer ids belong to robot 0; split them
among robots with :func:`kimera_multi_py.io.pose_graph.split_contiguous`.

The g2o information matrix is ordered ``[translation, rotation]``; it is stored here in gtsam's
``[rotation, translation]`` order, which is what ``gtsam.readG2o`` does too.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from kimera_multi_py.errors import DatasetError
from kimera_multi_py.geometry import make_pose, quat_to_rot, rot_to_quat
from kimera_multi_py.io.pose_graph import PoseGraph, split_key

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


def read_g2o(path: str | Path) -> PoseGraph:
    """Read a 3-D g2o file. Raises :class:`DatasetError` naming file and line on bad input.

    Symbol keys (>= 2**56) give the owning robot; otherwise every pose belongs to robot 0.
    Pose ids may have gaps: ``local`` is the rank of the id within its robot.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read g2o file: {exc}") from exc
    vertex_ids: list[int] = []
    vertex_vals: list[np.ndarray] = []
    vertex_line: dict[int, int] = {}
    edges: list[tuple[int, int, int, np.ndarray]] = []
    for lineno, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        tag = fields[0]
        if tag == "VERTEX_SE3:QUAT":
            if len(fields) < 2:
                raise DatasetError(f"{path}:{lineno}: VERTEX_SE3:QUAT without an id")
            vid = _pose_id(path, lineno, fields[1])
            if vid in vertex_line:
                raise DatasetError(
                    f"{path}:{lineno}: duplicate vertex {vid} (first on line {vertex_line[vid]})"
                )
            vals = _numbers(path, lineno, fields[2:], 7, tag)
            vertex_line[vid] = lineno
            vertex_ids.append(vid)
            vertex_vals.append(vals)
        elif tag == "EDGE_SE3:QUAT":
            if len(fields) < 3:
                raise DatasetError(f"{path}:{lineno}: EDGE_SE3:QUAT without two pose ids")
            a, b = _pose_id(path, lineno, fields[1]), _pose_id(path, lineno, fields[2])
            if a == b:
                raise DatasetError(f"{path}:{lineno}: edge from pose {a} to itself")
            vals = _numbers(path, lineno, fields[3:], 28, tag)
            edges.append((lineno, a, b, vals))
        elif tag in ("FIX", "PARAMS_SE3OFFSET"):
            log.debug("%s:%d: ignoring %s", path, lineno, tag)
        elif tag.startswith(("VERTEX_SE2", "EDGE_SE2", "VERTEX_XY", "EDGE_SE2_XY")):
            raise DatasetError(f"{path}:{lineno}: 2-D tag {tag} (only SE(3) graphs are supported)")
        else:
            raise DatasetError(f"{path}:{lineno}: unknown g2o tag {tag!r}")
    if not vertex_ids:
        raise DatasetError(f"{path}: no VERTEX_SE3:QUAT lines")

    ids = np.array(vertex_ids, dtype=np.int64)
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
            if not 0 <= r < 26:
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

    index = {vid: k for k, vid in enumerate(vertex_ids)}
    poses = np.stack([_pose_from(path, vertex_line[v], x)
                      for v, x in zip(vertex_ids, vertex_vals, strict=True)])
    m = len(edges)
    edge_i = np.zeros(m, dtype=int)
    edge_j = np.zeros(m, dtype=int)
    meas = np.zeros((m, 4, 4))
    info = np.zeros((m, 6, 6))
    indefinite = 0
    for e, (lineno, a, b, vals) in enumerate(edges):
        for v in (a, b):
            if v not in index:
                raise DatasetError(f"{path}:{lineno}: edge refers to pose {v}, which has no vertex")
        edge_i[e], edge_j[e] = index[a], index[b]
        meas[e] = _pose_from(path, lineno, vals[:7])
        info[e] = information_from_g2o(vals[7:])
        if np.linalg.eigvalsh(info[e])[0] <= 0.0:
            info[e] = _gtsam_information(path, lineno, info[e])
            indefinite += 1
    if indefinite:
        log.warning("%s: %d information matrices are not positive definite; using gtsam's "
                    "careful Cholesky factor R'R as gtsam.readG2o does", path, indefinite)
    _check_odometry(path, robot, local, edge_i, edge_j)
    return PoseGraph(poses=poses, robot=robot, local=local, ids=ids, edge_i=edge_i,
                     edge_j=edge_j, measurement=meas, information=info, source=path.name)


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
    """Write ``graph`` (with ``poses`` in place of its initial values) using its source ids."""
    poses = graph.poses if poses is None else np.asarray(poses, dtype=float)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    q = rot_to_quat(poses[:, :3, :3])
    qm = rot_to_quat(graph.measurement[:, :3, :3])
    lines = []
    for k in range(graph.num_poses):
        t = poses[k, :3, 3]
        lines.append(
            f"VERTEX_SE3:QUAT {int(graph.ids[k])} "
            + " ".join(f"{v:.9g}" for v in (*t, *q[k]))
        )
    for e in range(graph.num_edges):
        vals = (*graph.measurement[e, :3, 3], *qm[e], *information_to_g2o(graph.information[e]))
        lines.append(
            f"EDGE_SE3:QUAT {int(graph.ids[graph.edge_i[e]])} {int(graph.ids[graph.edge_j[e]])} "
            + " ".join(f"{v:.9g}" for v in vals)
        )
    path.write_text("\n".join(lines) + "\n")
