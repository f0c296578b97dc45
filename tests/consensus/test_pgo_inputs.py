"""The ``pgo`` command on inputs nobody here made: 2-D graphs, binary files, robust runs whose
outliers are unknown."""

from __future__ import annotations

import json
import os
from pathlib import Path

import gtsam
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from kimera_multi_py.cli.pgo import register
from kimera_multi_py.io.g2o import read_g2o, write_g2o
from kimera_multi_py.io.tum import read_tum
from kimera_multi_py.workflow.pgo_benchmark import inject_outliers, load_graph, run_pgo

GTSAM_DATA = Path(os.path.dirname(gtsam.__file__)) / "Data"


def cli() -> typer.Typer:
    app = typer.Typer()
    register(app)

    @app.callback()
    def _root() -> None:
        """kimera-multi"""

    return app


def test_2d_graph_gives_2d_outputs(tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = CliRunner().invoke(cli(), ["pgo", str(GTSAM_DATA / "pose2example.txt"), "--robots",
                                        "2", "--out", str(out), "--json", str(tmp_path / "r.json")])
    assert result.exit_code == 0, result.output
    fig = json.loads((tmp_path / "r.json").read_text())
    assert fig["robots"] == 2 and abs(fig["relative_gap"]) <= 1e-4
    text = (out / "distributed.g2o").read_text()
    assert "VERTEX_SE2" in text and "SE3" not in text
    assert read_g2o(out / "distributed.g2o").planar
    for r in range(2):
        _, poses = read_tum(out / f"robot{r}.tum")
        assert np.all(poses[:, 2, 3] == 0.0)  # z = 0
        np.testing.assert_allclose(poses[:, 2, :3], [[0, 0, 1]] * len(poses), atol=1e-12)


def test_binary_input_is_one_line_and_exit_1(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    path.write_bytes(bytes(range(256)))
    result = CliRunner().invoke(cli(), ["pgo", str(path)])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "not a text g2o file" in lines[0]
    assert "Traceback" not in result.output


@pytest.mark.slow
def test_robust_run_on_a_file_with_unknown_outliers(tmp_path: Path, pgo_data: Path) -> None:
    # outliers written into a g2o file: the run cannot know which edges they are
    g = inject_outliers(load_graph([pgo_data / "smallGrid3D.g2o"], 3), 0.5, seed=2)
    write_g2o(tmp_path / "dirty.g2o", g.with_robots(np.zeros(g.num_poses, dtype=int)))
    res = run_pgo([tmp_path / "dirty.g2o"], robots=3, robust=True, max_rounds=600)
    fig = res.to_json()
    assert not fig["truth_known"] and res.outliers == 0
    for key in ("inlier_precision", "inlier_recall", "precision_recall", "gap_to_outlier_free"):
        assert key not in fig
    assert fig["centralized_cost"] is None and fig["relative_gap"] is None
    assert fig["inlier_jaccard"] >= 0.95 and abs(fig["tls_gap"]) <= 1e-2
    counts = fig["inlier_counts"]["inter_robot"]
    # what the truth says (known here, not to the run): the kept inter-robot edges are the
    # true ones, by count and by index
    true_inter = int((~g.outlier & (g.edge_kind() == 2)).sum())
    assert counts["edges"] == true_inter + int(g.outlier.sum())
    assert counts["inliers_distributed"] == counts["inliers_centralized"] == true_inter
    true_closures = np.flatnonzero(~g.outlier & (g.edge_kind() != 0))
    assert set(fig["inlier_sets"]["distributed"]) == set(true_closures.tolist())
    assert fig["distributed_kept_cost"] == pytest.approx(fig["centralized_kept_cost"], rel=1e-3)
