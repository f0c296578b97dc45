"""Centralised reference: costs match datasets/README.md; chordal per component; GNC."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.core.posegraph import INTER_ROBOT
from kimera_multi_py.io.g2o import read_g2o
from kimera_multi_py.pgo.centralised import components, solve_centralized
from kimera_multi_py.pgo.factors import CostEvaluator, graph_cost, residuals_sq
from kimera_multi_py.workflow.pgo_benchmark import inject_outliers, load_graph


@pytest.mark.parametrize(("name", "cost"), [("tinyGrid3D", 9.31391), ("smallGrid3D", 517.925)])
def test_reference_costs(pgo_data: Path, name: str, cost: float) -> None:
    res = solve_centralized(read_g2o(pgo_data / f"{name}.g2o"))
    assert res.init == "chordal"
    assert res.cost == pytest.approx(cost, rel=1e-5)
    assert res.initial_cost > res.cost


def test_two_robot_files_are_two_components(pgo_data: Path) -> None:
    g = load_graph([pgo_data / "robot_a.g2o", pgo_data / "robot_b.g2o"])
    assert len(components(g)) == 2 and g.num_robots == 2
    res = solve_centralized(g)
    assert res.cost < res.initial_cost


def test_numpy_cost_matches_gtsam(pgo_data: Path) -> None:
    g = read_g2o(pgo_data / "smallGrid3D.g2o")
    assert graph_cost(g, g.poses) == pytest.approx(CostEvaluator(g)(g.poses), rel=1e-9)
    assert residuals_sq(g, g.poses).sum() == pytest.approx(2 * graph_cost(g, g.poses), rel=1e-9)


@pytest.mark.slow
def test_gnc_rejects_injected_outliers(pgo_data: Path) -> None:
    g = inject_outliers(load_graph([pgo_data / "smallGrid3D.g2o"], 5), 0.5, seed=0)
    inter = g.edge_kind() == INTER_ROBOT
    assert g.outlier.sum() == round(0.5 * (inter & ~g.outlier).sum())
    res = solve_centralized(g, robust=True)
    assert res.weights is not None
    assert np.all(res.weights[g.outlier] < 0.5)
    assert np.all(res.weights[~g.outlier] >= 0.5)  # and no true edge (closure or odometry) lost
    free = solve_centralized(g.subset_edges(~g.outlier))
    assert res.cost == pytest.approx(free.cost, rel=1e-2)
