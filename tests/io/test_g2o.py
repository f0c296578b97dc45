"""g2o reading, splitting, writing and every malformed-input case."""

from __future__ import annotations

import logging
from pathlib import Path

import gtsam
import numpy as np
import pytest

from kimera_multi_py.core.errors import DatasetError
from kimera_multi_py.core.posegraph import (
    INTER_ROBOT,
    LOOP_CLOSURE,
    ODOMETRY,
    merge_graphs,
    robot_key,
    split_contiguous,
    split_key,
)
from kimera_multi_py.io.g2o import read_g2o, write_g2o

VERTEX = "VERTEX_SE3:QUAT {} {} 0 0 0 0 0 1"
INFO = " ".join(["100 0 0 0 0 0", "100 0 0 0 0", "100 0 0 0", "400 0 0", "400 0", "400"])
EDGE = "EDGE_SE3:QUAT {} {} 1 0 0 0 0 0 1 " + INFO


def chain(n: int) -> list[str]:
    return [VERTEX.format(k, k) for k in range(n)] + [EDGE.format(k, k + 1) for k in range(n - 1)]


def write(tmp_path: Path, lines: list[str]) -> Path:
    path = tmp_path / "g.g2o"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_reads_tiny_grid_like_gtsam(pgo_data: Path) -> None:
    path = pgo_data / "tinyGrid3D.g2o"
    g = read_g2o(path)
    assert (g.num_poses, g.num_edges, g.num_robots) == (9, 11, 1)
    fg, values = gtsam.readG2o(str(path), True)
    ours = gtsam.NonlinearFactorGraph()
    from kimera_multi_py.pgo.factors import between, to_values

    for e in range(g.num_edges):
        ours.add(between(int(g.ids[g.edge_i[e]]), int(g.ids[g.edge_j[e]]), g.measurement[e],
                         g.information[e]))
    assert ours.error(to_values(g.ids, g.poses)) == pytest.approx(fg.error(values), rel=1e-9)


def test_multi_robot_symbol_keys(pgo_data: Path) -> None:
    a = read_g2o(pgo_data / "robot_a.g2o")
    b = read_g2o(pgo_data / "robot_b.g2o")
    assert set(a.robot) == {0} and set(b.robot) == {1}
    ab = merge_graphs([a, b])
    assert ab.num_robots == 2 and ab.num_poses == 92
    assert split_key(int(ab.keys[60])) == (1, 10)
    assert gtsam.Symbol(int(ab.keys[60])).string() == "b10"
    kinds = ab.edge_kind()
    assert (kinds == ODOMETRY).sum() == 49 + 41 and (kinds == INTER_ROBOT).sum() == 0


def test_split_contiguous_makes_blocks_and_inter_robot_edges(pgo_data: Path) -> None:
    g = split_contiguous(read_g2o(pgo_data / "smallGrid3D.g2o"), 5)
    assert np.bincount(g.robot).tolist() == [25] * 5
    assert np.all(np.diff(g.robot[np.argsort(g.ids)]) >= 0)
    kinds = g.edge_kind()
    assert (kinds == INTER_ROBOT).sum() > 0 and (kinds == LOOP_CLOSURE).sum() > 0
    assert g.keys[0] == robot_key(0, 0)


def test_round_trip(tmp_path: Path, pgo_data: Path) -> None:
    g = read_g2o(pgo_data / "tinyGrid3D.g2o")
    write_g2o(tmp_path / "out.g2o", g)
    h = read_g2o(tmp_path / "out.g2o")
    np.testing.assert_allclose(h.poses, g.poses, atol=1e-7)
    np.testing.assert_allclose(h.information, g.information, rtol=1e-8)
    np.testing.assert_allclose(h.measurement, g.measurement, atol=1e-7)


def test_gaps_in_ids_are_renumbered_by_rank(tmp_path: Path, caplog) -> None:
    lines = [VERTEX.format(k, k) for k in (0, 1, 5, 6)]
    lines += [EDGE.format(0, 1), EDGE.format(1, 5), EDGE.format(6, 5)]
    with caplog.at_level(logging.INFO):
        g = read_g2o(write(tmp_path, lines))
    assert g.local.tolist() == [0, 1, 2, 3]
    assert (g.edge_kind() == ODOMETRY).all()  # 1->5 bridges the gap, 6->5 runs backwards
    assert "gaps" in caplog.text and "backwards" in caplog.text


def test_indefinite_information_uses_gtsam_factor(tmp_path: Path) -> None:
    # cubicle.g2o has such matrices: gtsam keeps the careful Cholesky factor R with R'R != I
    info = " ".join(["10 0 0 0 0 5", "10 0 0 0 0", "10 0 0 0", "10 0 0", "10 0", "1"])
    path = write(tmp_path, chain(2)[:2] + ["EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + info])
    g = read_g2o(path)
    model = gtsam.noiseModel.Gaussian.Information(np.asarray(g.information[0]))
    assert np.linalg.eigvalsh(g.information[0]).min() >= -1e-9
    np.testing.assert_allclose(model.R().T @ model.R(), g.information[0], atol=1e-9)


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        (chain(2) + ["EDGE_SE3:QUAT 0 1 1 0 0"], ":4: EDGE_SE3:QUAT needs 28 values"),
        (chain(2) + [VERTEX.format(1, 1)], ":4: duplicate vertex 1 (first on line 2)"),
        (chain(2) + [EDGE.format(0, 7)], ":4: edge refers to pose 7"),
        (chain(2) + [EDGE.format(1, 1)], ":4: edge from pose 1 to itself"),
        (["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", "VERTEX_SE3:QUAT 1 0 0 x 0 0 0 1"],
         ":2: non-numeric value"),
        (["VERTEX_SE3:QUAT 0 0 0 nan 0 0 0 1"], ":1: non-finite"),
        (["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0"], ":1: quaternion norm"),
        (["VERTEX_SE3:QUAT a 0 0 0 0 0 0 1"], ":1: pose id 'a' is not an integer"),
        (["VERTEX_SE3:QUAT -3 0 0 0 0 0 0 1"], ":1: negative pose id"),
        (chain(2) + ["EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1"], ":4: EDGE_SE2 mixes 2-D and 3-D tags"),
        (chain(2) + ["EDGE3 0 1 1 0 0 0 0"], ":4: EDGE3 needs 27 values"),
        (chain(2) + ["EDGE_SE2_XY 0 1 1 0 1 0 1"], ":4: unknown landmark tag"),
        (chain(2) + ["BOGUS 1 2"], ":4: unknown g2o tag"),
        (["# only a comment"], "no vertices and no edges"),
        ([VERTEX.format(0, 0), f"VERTEX_SE3:QUAT {robot_key(1, 0)} 0 0 0 0 0 0 1"],
         "mixes gtsam Symbol keys"),
        (chain(2) + ["EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + INFO.replace("100", "-5", 1)],
         ":4: information matrix has a non-positive diagonal"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path: Path, lines: list[str],
                                            message: str) -> None:
    path = write(tmp_path, lines)
    with pytest.raises(DatasetError) as err:
        read_g2o(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="cannot read"):
        read_g2o(tmp_path / "nope.g2o")
