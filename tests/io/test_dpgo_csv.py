"""DPGO multi-robot CSV: round trip through a split g2o, de-duplication, malformed rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.consensus.factors import graph_cost
from kimera_multi_py.errors import DatasetError
from kimera_multi_py.io.dpgo_csv import COLUMNS, read_dpgo_csv, write_dpgo_csv
from kimera_multi_py.io.g2o import read_g2o
from kimera_multi_py.io.pose_graph import INTER_ROBOT, split_contiguous

HEADER = ",".join(COLUMNS)
ROW = "{},{},{},{},0,0,0,1,1,0,0,50,100,1,1"


def make(tmp_path: Path, files: dict[int, list[str]]) -> Path:
    for r, rows in files.items():
        p = tmp_path / f"robot{r}" / "measurements.csv"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("\n".join([HEADER, *rows]) + "\n")
    return tmp_path


def test_round_trip_of_split_grid(tmp_path: Path, datasets_dir: Path) -> None:
    g = split_contiguous(read_g2o(datasets_dir / "pgo" / "smallGrid3D.g2o"), 3)
    write_dpgo_csv(tmp_path, g)
    h = read_dpgo_csv(tmp_path)
    assert h.num_robots == 3 and h.num_poses == g.num_poses
    assert h.num_edges == g.num_edges  # inter-robot rows are in two files but kept once
    assert (h.edge_kind() == INTER_ROBOT).sum() == (g.edge_kind() == INTER_ROBOT).sum()
    # isotropic information diag(2κ, τ); the grid's information is isotropic per block
    np.testing.assert_allclose(np.sort(h.information.ravel()), np.sort(g.information.ravel()))
    # initial poses chain the odometry from each robot's first pose: zero odometry residual
    odo = h.edge_kind() == 0
    assert graph_cost(h, h.poses, odo) == pytest.approx(0.0, abs=1e-9)


def test_duplicate_inter_robot_rows_kept_once(tmp_path: Path) -> None:
    folder = make(tmp_path, {0: [ROW.format(0, 0, 0, 1), ROW.format(0, 1, 1, 0)],
                             1: [ROW.format(1, 0, 1, 1), ROW.format(0, 1, 1, 0)]})
    g = read_dpgo_csv(folder)
    assert g.num_edges == 3 and g.num_poses == 4
    np.testing.assert_allclose(np.diag(g.information[0]), [100, 100, 100, 100, 100, 100])


@pytest.mark.parametrize(
    ("rows", "message"),
    [
        ([ROW.format(0, 0, 0, 1) + ",7"], "robot0/measurements.csv:2: expected 15 columns"),
        (["0,0,0,x,0,0,0,1,1,0,0,50,100,1,1"], ":2: non-numeric value"),
        (["0,0,0,1,0,0,0,1,nan,0,0,50,100,1,1"], ":2: non-finite value"),
        (["0,0,0,1,0,0,0,2,1,0,0,50,100,1,1"], ":2: quaternion is not unit norm"),
        (["0,0,0,1,0,0,0,1,1,0,0,0,100,1,1"], ":2: kappa and tau must be positive"),
        (["0,0,0,1,0,0,0,1,1,0,0,50,100,3,1"], ":2: is_known_inlier must be 0 or 1"),
        ([ROW.format(0, 1, 0, 1)], ":2: measurement from a pose to itself"),
        ([ROW.format(0, 0, 0, 1), ROW.format(2, 0, 2, 1)], ":3: row involves neither robot 0"),
        (["-1,0,0,1,0,0,0,1,1,0,0,50,100,1,1"], ":2: negative robot or pose id"),
    ],
)
def test_malformed_rows(tmp_path: Path, rows: list[str], message: str) -> None:
    folder = make(tmp_path, {0: rows})
    with pytest.raises(DatasetError, match=message.replace("(", r"\(")):
        read_dpgo_csv(folder)


def test_conflicting_duplicates_and_bad_header(tmp_path: Path) -> None:
    folder = make(tmp_path / "a", {0: [ROW.format(0, 0, 1, 0)],
                                   1: [ROW.format(0, 0, 1, 0).replace(",1,0,0,50", ",2,0,0,50")]})
    with pytest.raises(DatasetError, match="robot1/measurements.csv:2: disagrees"):
        read_dpgo_csv(folder)
    bad = tmp_path / "b" / "robot0" / "measurements.csv"
    bad.parent.mkdir(parents=True)
    bad.write_text("a,b,c\n")
    with pytest.raises(DatasetError, match="measurements.csv:1: header"):
        read_dpgo_csv(tmp_path / "b")
    with pytest.raises(DatasetError, match="no robotK"):
        read_dpgo_csv(tmp_path / "empty")
