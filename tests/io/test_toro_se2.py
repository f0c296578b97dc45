"""TORO 3-D (``VERTEX3``/``EDGE3``), 2-D g2o (``VERTEX_SE2``/``EDGE_SE2``) and binary input,
on gtsam's own data files where they exist."""

from __future__ import annotations

import os
from pathlib import Path

import gtsam
import numpy as np
import pytest

from kimera_multi_py.core.errors import DatasetError
from kimera_multi_py.core.geometry import from_gtsam
from kimera_multi_py.core.posegraph import PoseGraph
from kimera_multi_py.io.g2o import read_g2o, write_g2o
from kimera_multi_py.io.planar import pose_to_se2
from kimera_multi_py.pgo.centralised import solve_centralized
from kimera_multi_py.pgo.factors import graph_cost

GTSAM_DATA = Path(os.path.dirname(gtsam.__file__)) / "Data"


def edge_map(g: PoseGraph) -> dict[tuple[int, int], int]:
    return {(int(g.ids[i]), int(g.ids[j])): e for e, (i, j) in
            enumerate(zip(g.edge_i, g.edge_j, strict=True))}


def test_toro_sphere2500_is_the_g2o_sphere2500(datasets_dir: Path) -> None:
    # gtsam ships sphere2500 as TORO EDGE3 lines only (no vertices); the datasets folder has the g2o
    # conversion of the same graph (with g2o's quaternion information, 4x TORO's on rotation)
    toro = read_g2o(GTSAM_DATA / "sphere2500.txt")
    ref = read_g2o(datasets_dir / "pgo" / "sphere2500.g2o")
    assert (toro.num_poses, toro.num_edges) == (ref.num_poses, ref.num_edges) == (2500, 4949)
    assert not toro.planar
    ours, theirs = edge_map(toro), edge_map(ref)
    assert ours.keys() == theirs.keys()
    e_t = np.array([ours[k] for k in theirs])
    e_r = np.array(list(theirs.values()))
    np.testing.assert_allclose(toro.measurement[e_t], ref.measurement[e_r], atol=1e-5)
    # information over [t, R] in the file (as g2o's): translation equal, rotation a quarter
    d_t = np.diagonal(toro.information[e_t], axis1=1, axis2=2)
    d_r = np.diagonal(ref.information[e_r], axis1=1, axis2=2)
    np.testing.assert_allclose(d_t[:, 3:], d_r[:, 3:], rtol=1e-9)
    np.testing.assert_allclose(d_r[:, :3] / d_t[:, :3], 4.0, rtol=5e-2)
    # no vertices: the initial values chain the odometry, as the g2o file's do
    np.testing.assert_allclose(toro.poses, ref.poses, atol=1e-2)


def test_toro_vertex_and_edge_match_gtsam_rpy(tmp_path: Path) -> None:
    info = " ".join(["10 0 0 0 0 0", "20 0 0 0 0", "30 0 0 0", "1 0 0", "2 0", "3"])
    path = tmp_path / "g.graph"
    path.write_text("VERTEX3 0 0 0 0 0 0 0\nVERTEX3 1 1 2 3 0.1 -0.2 0.3\n"
                    f"EDGE3 0 1 1 2 3 0.1 -0.2 0.3 {info}\n")
    g = read_g2o(path)
    R = gtsam.Rot3.Ypr(0.3, -0.2, 0.1).matrix()
    np.testing.assert_allclose(g.poses[1, :3, :3], R, atol=1e-12)
    np.testing.assert_allclose(g.measurement[0], g.poses[1], atol=1e-12)
    # gtsam order [R, t]: the file's translation block (10, 20, 30) goes last
    np.testing.assert_allclose(np.diag(g.information[0]), [1, 2, 3, 10, 20, 30])


def test_se2_graph_has_gtsam_pose2_cost_and_optimum(tmp_path: Path) -> None:
    path = GTSAM_DATA / "pose2example.txt"
    g = read_g2o(path)
    assert g.planar and (g.num_poses, g.num_edges) == (11, 12)
    fg, values = gtsam.readG2o(str(path), False)  # gtsam's own SE(2) reading
    assert graph_cost(g, g.poses) == pytest.approx(fg.error(values), rel=1e-9)
    fg.add(gtsam.PriorFactorPose2(0, values.atPose2(0), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    opt = gtsam.LevenbergMarquardtOptimizer(fg, values).optimize()
    res = solve_centralized(g)
    assert res.cost == pytest.approx(fg.error(opt), rel=1e-6)
    # the planar SE(3) optimum stays in the plane and is gtsam's Pose2 optimum
    assert np.abs(res.poses[:, 2, 3]).max() < 1e-9
    assert np.abs(res.poses[:, 2, :2]).max() < 1e-9
    pose2 = np.array([[opt.atPose2(k).x(), opt.atPose2(k).y(), opt.atPose2(k).theta()]
                      for k in range(11)])
    ours = pose_to_se2(res.poses)
    ours[:, :2] -= ours[:1, :2] - pose2[:1, :2]
    np.testing.assert_allclose(ours, pose2, atol=1e-5)
    # written back as 2-D g2o, read equal
    write_g2o(tmp_path / "out.g2o", g, res.poses)
    text = (tmp_path / "out.g2o").read_text()
    assert text.startswith("VERTEX_SE2 ") and "EDGE_SE2 " in text and "SE3" not in text
    h = read_g2o(tmp_path / "out.g2o")
    np.testing.assert_allclose(h.poses, res.poses, atol=1e-7)
    np.testing.assert_allclose(h.information, g.information, rtol=1e-8)
    np.testing.assert_allclose(h.measurement, g.measurement, atol=1e-8)


def test_se2_edge_information_order(tmp_path: Path) -> None:
    path = tmp_path / "g.g2o"
    path.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 1.5\n"
                    "EDGE_SE2 0 1 1 0 1.5 11 12 13 22 23 33\n")
    g = read_g2o(path)
    info = g.information[0]
    np.testing.assert_allclose(info[np.ix_([3, 4, 2], [3, 4, 2])],
                               [[11, 12, 13], [12, 22, 23], [13, 23, 33]])
    np.testing.assert_allclose(info[[0, 1, 5], [0, 1, 5]], 33.0)  # out of plane: the largest
    np.testing.assert_allclose(g.poses[1], from_gtsam(gtsam.Pose3(gtsam.Pose2(1, 0, 1.5))),
                               atol=1e-12)


@pytest.mark.parametrize(("data", "message"), [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "not a text g2o file (binary data at byte 8)"),
    (b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n\xff\xfe", "undecodable byte at offset 32"),
])
def test_binary_input_is_one_dataset_error(tmp_path: Path, data: bytes, message: str) -> None:
    path = tmp_path / "g.g2o"
    path.write_bytes(data)
    with pytest.raises(DatasetError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_g2o(path)
