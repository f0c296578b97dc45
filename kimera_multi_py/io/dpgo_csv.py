"""DPGO's multi-robot CSV layout: ``robotK/measurements.csv`` per robot.

Columns: ``robot_src,pose_src,robot_dst,pose_dst,qx,qy,qz,qw,tx,ty,tz,kappa,tau,
is_known_inlier,weight``. An inter-robot row appears in both robots' files and is kept once; the
two copies are compared without ``weight`` (a previous solver's GNC weight, which differs
between the copies of real files), and any other disagreement is a warning (first copy kept).

DPGO's cost ``κ‖R_j − R_i R_ij‖²_F + τ‖t_j − t_i − R_i t_ij‖²`` matches a Gaussian with
information ``diag(2κ I₃, τ I₃)`` in gtsam's ``[rotation, translation]`` order (DPGO's own g2o
reader uses ``κ = 3 / (2 tr Σ_R)`` and ``τ = 3 / tr Σ_t``). The files carry no initial values,
so each robot's poses are initialised by chaining its own measurements from pose 0.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from kimera_multi_py.core.errors import DatasetError
from kimera_multi_py.core.geometry import make_pose, quat_to_rot, rot_to_quat
from kimera_multi_py.core.ids import MAX_AGENT_ID
from kimera_multi_py.core.posegraph import PoseGraph, chain_odometry, robot_key
from kimera_multi_py.io.text import read_text

log = logging.getLogger(__name__)

COLUMNS = (
    "robot_src", "pose_src", "robot_dst", "pose_dst", "qx", "qy", "qz", "qw",
    "tx", "ty", "tz", "kappa", "tau", "is_known_inlier", "weight",
)
_ROBOT_DIR = re.compile(r"^robot(\d+)$")


def _parse_row(path: Path, lineno: int, fields: list[str]) -> tuple[tuple[int, ...], np.ndarray]:
    if len(fields) != len(COLUMNS):
        raise DatasetError(f"{path}:{lineno}: expected {len(COLUMNS)} columns, got {len(fields)}")
    try:
        ints = tuple(int(f) for f in fields[:4])
        vals = np.array([float(f) for f in fields[4:]])
    except ValueError:
        raise DatasetError(f"{path}:{lineno}: non-numeric value") from None
    if min(ints) < 0:
        raise DatasetError(f"{path}:{lineno}: negative robot or pose id")
    if not np.all(np.isfinite(vals)):
        raise DatasetError(f"{path}:{lineno}: non-finite value")
    if abs(np.linalg.norm(vals[:4]) - 1.0) > 1e-3:
        raise DatasetError(f"{path}:{lineno}: quaternion is not unit norm")
    if vals[7] <= 0 or vals[8] <= 0:
        raise DatasetError(f"{path}:{lineno}: kappa and tau must be positive")
    if vals[9] not in (0.0, 1.0):
        raise DatasetError(f"{path}:{lineno}: is_known_inlier must be 0 or 1")
    if ints[:2] == ints[2:]:
        raise DatasetError(f"{path}:{lineno}: measurement from a pose to itself")
    return ints, vals


def read_dpgo_csv(folder: str | Path) -> PoseGraph:
    """Read every ``robotK/measurements.csv`` under ``folder`` into one graph."""
    folder = Path(folder)
    files = sorted(
        (int(m.group(1)), p / "measurements.csv")
        for p in (folder.iterdir() if folder.is_dir() else [])
        if (m := _ROBOT_DIR.match(p.name)) and (p / "measurements.csv").is_file()
    )
    if not files:
        raise DatasetError(f"{folder}: no robotK/measurements.csv files")
    rows: dict[tuple[int, ...], tuple[np.ndarray, str]] = {}
    for robot, path in files:
        lines = read_text(path, "DPGO measurements file").splitlines()
        if not lines or [c.strip() for c in lines[0].split(",")] != list(COLUMNS):
            raise DatasetError(f"{path}:1: header must be {','.join(COLUMNS)}")
        for lineno, line in enumerate(lines[1:], 2):
            if not line.strip():
                continue
            ints, vals = _parse_row(path, lineno, [f.strip() for f in line.split(",")])
            if robot not in (ints[0], ints[2]):
                raise DatasetError(f"{path}:{lineno}: row involves neither robot {robot}")
            where = f"{path}:{lineno}"
            if ints in rows:
                _check_duplicate(rows[ints], vals, where)
                continue
            rows[ints] = (vals, where)
    return _build(folder, rows)


def _check_duplicate(first: tuple[np.ndarray, str], vals: np.ndarray, where: str) -> None:
    """An inter-robot row read a second time (from the other robot's file). ``weight`` (the
    last column) is a previous solver's GNC weight, not part of the measurement: it is ignored.
    Any other disagreement is logged and the first copy kept."""
    old, first_where = first
    if not np.allclose(old[:-1], vals[:-1], rtol=1e-6, atol=1e-9):
        bad = [COLUMNS[4 + c] for c in np.flatnonzero(
            ~np.isclose(old[:-1], vals[:-1], rtol=1e-6, atol=1e-9))]
        log.warning("%s: disagrees with the same measurement at %s in %s; keeping the first",
                    where, first_where, ",".join(bad))


def _build(folder: Path, rows: dict[tuple[int, ...], tuple[np.ndarray, str]]) -> PoseGraph:
    keys = sorted({(r, p) for k in rows for r, p in (k[:2], k[2:])})
    index = {k: n for n, k in enumerate(keys)}
    robot = np.array([k[0] for k in keys], dtype=int)
    pose_id = np.array([k[1] for k in keys], dtype=int)
    local = np.zeros(len(keys), dtype=int)
    for r in np.unique(robot):
        idx = np.flatnonzero(robot == r)  # already sorted by pose id
        local[idx] = np.arange(len(idx))
        if pose_id[idx[-1]] + 1 != len(idx):
            log.warning("%s: robot %d has gaps in pose ids; poses renumbered by rank", folder, r)
    if robot.max() > MAX_AGENT_ID:
        raise DatasetError(f"{folder}: robot id {robot.max()} exceeds {MAX_AGENT_ID}")
    m = len(rows)
    edge_i, edge_j = np.zeros(m, dtype=int), np.zeros(m, dtype=int)
    meas, info = np.zeros((m, 4, 4)), np.zeros((m, 6, 6))
    for e, (k, (vals, _)) in enumerate(rows.items()):
        edge_i[e], edge_j[e] = index[(k[0], k[1])], index[(k[2], k[3])]
        meas[e] = make_pose(quat_to_rot(vals[:4]), vals[4:7])
        info[e] = np.diag([2 * vals[7]] * 3 + [vals[8]] * 3)
    poses = chain_odometry(str(folder), robot, edge_i, edge_j, meas)
    ids = np.array([robot_key(int(r), int(p)) for r, p in keys], dtype=np.int64)
    return PoseGraph(poses=poses, robot=robot, local=local, ids=ids, edge_i=edge_i,
                     edge_j=edge_j, measurement=meas, information=info, source=folder.name)


def write_dpgo_csv(folder: str | Path, graph: PoseGraph) -> None:
    """Write ``graph`` in DPGO's layout (isotropic κ, τ fitted to each information matrix)."""
    folder = Path(folder)
    q = rot_to_quat(graph.measurement[:, :3, :3])
    cov = np.linalg.inv(graph.information)
    kappa = 3.0 / (2.0 * np.trace(cov[:, :3, :3], axis1=1, axis2=2))
    tau = 3.0 / np.trace(cov[:, 3:, 3:], axis1=1, axis2=2)
    ri, rj = graph.robot[graph.edge_i], graph.robot[graph.edge_j]
    li, lj = graph.local[graph.edge_i], graph.local[graph.edge_j]
    for r in range(graph.num_robots):
        lines = [",".join(COLUMNS)]
        for e in np.flatnonzero((ri == r) | (rj == r)):
            t = graph.measurement[e, :3, 3]
            known = 1 if (ri[e] == rj[e] and abs(li[e] - lj[e]) == 1) else 0
            vals = [ri[e], li[e], rj[e], lj[e]]
            lines.append(",".join(
                [str(int(v)) for v in vals]
                + [f"{v:.12g}" for v in (*q[e], *t, kappa[e], tau[e])]
                + [str(known), "1"]
            ))
        path = folder / f"robot{r}" / "measurements.csv"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n")
