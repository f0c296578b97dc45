"""DPGO multi-robot CSV: round trip through a split g2o, de-duplication, malformed rows."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.core.errors import DatasetError
from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.core.posegraph import (
    INTER_ROBOT,
    LOOP_CLOSURE,
    ODOMETRY,
    PoseGraph,
    split_contiguous,
)
from kimera_multi_py.io.dpgo_csv import COLUMNS, read_dpgo_csv, write_dpgo_csv
from kimera_multi_py.io.g2o import read_g2o
from kimera_multi_py.pgo.factors import graph_cost

HEADER = ",".join(COLUMNS)
ROW = "{},{},{},{},0,0,0,1,1,0,0,50,100,1,1"


def make(tmp_path: Path, files: dict[int, list[str]]) -> Path:
    for r, rows in files.items():
        p = tmp_path / f"robot{r}" / "measurements.csv"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("\n".join([HEADER, *rows]) + "\n")
    return tmp_path


def flip(g: PoseGraph, edges: np.ndarray) -> PoseGraph:
    """``g`` with ``edges`` reversed: ``j -> i`` measuring ``Z⁻¹`` (the same information)."""
    ei, ej, meas = g.edge_i.copy(), g.edge_j.copy(), g.measurement.copy()
    ei[edges], ej[edges] = g.edge_j[edges], g.edge_i[edges]
    meas[edges] = inverse(g.measurement[edges])
    return replace(g, edge_i=ei, edge_j=ej, measurement=meas)


def test_round_trip_keeps_every_edge(tmp_path: Path, pgo_data: Path) -> None:
    g = split_contiguous(read_g2o(pgo_data / "smallGrid3D.g2o"), 3)
    kind = g.edge_kind()
    # written backwards: an inter-robot edge from a higher robot to a lower one, a loop
    # closure from a later pose to an earlier one, and an odometry step j -> j-1
    inter, loop, odo = (np.flatnonzero(kind == k) for k in (INTER_ROBOT, LOOP_CLOSURE, ODOMETRY))
    g = flip(g, np.concatenate([inter[:5], loop[:5], odo[3:4]]))
    assert np.any(g.robot[g.edge_i] > g.robot[g.edge_j])
    write_dpgo_csv(tmp_path, g)
    h = read_dpgo_csv(tmp_path)
    assert (h.num_robots, h.num_poses, h.num_edges) == (3, g.num_poses, g.num_edges)
    # every written edge comes back once, in its direction, with its measurement and its
    # information (the grid's is isotropic per block, so DPGO's diag(2κ, τ) holds it exactly)
    key_g = {(int(g.robot[i]), int(g.local[i]), int(g.robot[j]), int(g.local[j])): e
             for e, (i, j) in enumerate(zip(g.edge_i, g.edge_j, strict=True))}
    for e, (i, j) in enumerate(zip(h.edge_i, h.edge_j, strict=True)):
        k = (int(h.robot[i]), int(h.local[i]), int(h.robot[j]), int(h.local[j]))
        assert k in key_g, f"edge {k} was not written"
        written = key_g.pop(k)
        np.testing.assert_allclose(h.measurement[e], g.measurement[written], atol=1e-9)
        np.testing.assert_allclose(h.information[e], g.information[written], rtol=1e-9)
    assert not key_g
    # the same graph: equal cost at the same poses (h orders poses by (robot, local))
    order = np.lexsort((g.local, g.robot))
    assert graph_cost(h, g.poses[order]) == pytest.approx(graph_cost(g, g.poses), rel=1e-9)


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


def test_duplicates_differing_only_in_weight_are_one_edge(tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    # real DPGO files: the two copies of an inter-robot row differ in the weight column only
    row = ROW.format(0, 1, 1, 0)
    folder = make(tmp_path, {0: [ROW.format(0, 0, 0, 1), row[:-1] + "0.999997"],
                             1: [ROW.format(1, 0, 1, 1), row[:-1] + "0.999993"]})
    with caplog.at_level(logging.WARNING, logger="kimera_multi_py.io.dpgo_csv"):
        g = read_dpgo_csv(folder)
    assert g.num_edges == 3 and not caplog.records


def test_conflicting_duplicates_warn_and_keep_the_first(tmp_path: Path,
                                                        caplog: pytest.LogCaptureFixture) -> None:
    first = ROW.format(0, 0, 1, 0)
    folder = make(tmp_path, {0: [first], 1: [first.replace(",1,0,0,50", ",2,0,0,50")]})
    with caplog.at_level(logging.WARNING, logger="kimera_multi_py.io.dpgo_csv"):
        g = read_dpgo_csv(folder)
    assert g.num_edges == 1 and g.measurement[0, 0, 3] == 1.0
    assert "robot1/measurements.csv:2: disagrees" in caplog.text and "in tx" in caplog.text


def test_binary_file_is_a_dataset_error(tmp_path: Path) -> None:
    p = tmp_path / "robot0" / "measurements.csv"
    p.parent.mkdir(parents=True)
    p.write_bytes(HEADER.encode() + b"\n\x89PNG\r\n\x1a\n\x00\x00")
    with pytest.raises(DatasetError, match=r"measurements.csv: not a text .*binary data at byte"):
        read_dpgo_csv(tmp_path)
    p.write_bytes(HEADER.encode() + b"\n\xff\xfe0,0,0,1")
    with pytest.raises(DatasetError, match="undecodable byte at offset"):
        read_dpgo_csv(tmp_path)


def test_bad_header_and_empty_folder(tmp_path: Path) -> None:
    bad = tmp_path / "b" / "robot0" / "measurements.csv"
    bad.parent.mkdir(parents=True)
    bad.write_text("a,b,c\n")
    with pytest.raises(DatasetError, match="measurements.csv:1: header"):
        read_dpgo_csv(tmp_path / "b")
    with pytest.raises(DatasetError, match="no robotK"):
        read_dpgo_csv(tmp_path / "empty")
