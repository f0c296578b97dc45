"""Distributed pose-graph optimisation of a g2o file, against gtsam's centralised solve.

The graph's poses are split among ``--robots`` robots (contiguous blocks, unless the file already
uses gtsam Symbol keys per robot); each robot is a PGO agent on its own bus of one in-process
loopback network, and they solve together by message passing (docs/algorithms/pgo.md). Without a
file, a small synthetic helix of laps with loop closures between laps is written and solved.

    python examples/distributed_pgo.py [GRAPH.g2o] --robots 4 --method gn_pcg [--robust]

The ``kimera-multi pgo`` command does the same with more options and writes the solutions.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from kimera_multi_py.core.geometry import inverse, make_pose, rot_to_quat, so3_exp
from kimera_multi_py.workflow.pgo_benchmark import run_pgo

INFO = (100.0, 100.0, 100.0, 400.0, 400.0, 400.0)  # g2o order: translation, then rotation


def _edge(i: int, j: int, Z: np.ndarray) -> str:
    info = np.diag(INFO)[np.triu_indices(6)]
    return f"EDGE_SE3:QUAT {i} {j} " + " ".join(f"{v:.9g}" for v in (*Z[:3, 3], *rot_to_quat(Z[:3, :3]), *info))


def synthetic_g2o(path: Path, laps: int = 6, per_lap: int = 40, seed: int = 0) -> Path:
    """A helix of ``laps`` laps of ``per_lap`` poses; odometry and a closure to the pose one lap
    below, every 4th pose, both with noise; initial values are the chained noisy odometry."""
    rng = np.random.default_rng(seed)
    n = laps * per_lap
    a = 2 * np.pi * np.arange(n) / per_lap
    truth = [make_pose(so3_exp(np.array([0.0, 0.0, ak + np.pi / 2])),
                       np.array([5 * np.cos(ak), 5 * np.sin(ak), 0.3 * ak])) for ak in a]

    def noisy(Z: np.ndarray) -> np.ndarray:
        return Z @ make_pose(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.1, 3))

    odom = [noisy(inverse(truth[k - 1]) @ truth[k]) for k in range(1, n)]
    init = [truth[0].copy()]
    for Z in odom:
        init.append(init[-1] @ Z)
    lines = [f"VERTEX_SE3:QUAT {k} " + " ".join(f"{v:.9g}" for v in (*T[:3, 3], *rot_to_quat(T[:3, :3])))
             for k, T in enumerate(init)]
    lines += [_edge(k - 1, k, Z) for k, Z in enumerate(odom, start=1)]
    lines += [_edge(k - per_lap, k, noisy(inverse(truth[k - per_lap]) @ truth[k])) for k in range(per_lap, n, 4)]
    path.write_text("\n".join(lines) + "\n")
    return path


def main(graph: Path | None = None, robots: int = 4, method: str = "gn_pcg", robust: bool = False,
         max_rounds: int = 500) -> dict[str, object]:
    """Solve ``graph`` (or a synthetic helix) centrally and distributed; return the figures."""
    with tempfile.TemporaryDirectory() as tmp:
        path = graph if graph is not None else synthetic_g2o(Path(tmp) / "helix.g2o")
        result = run_pgo([path], robots=robots, robust=robust, max_rounds=max_rounds, method=method)
    out = result.to_json()
    keep = ("dataset", "robots", "centralized_cost", "distributed_cost", "relative_gap", "rounds",
            "rounds_to_1e-3", "bytes_sent", "wall_s", "centralized_tls_cost", "distributed_tls_cost",
            "tls_gap", "inlier_jaccard")
    return {k: out[k] for k in keep if k in out}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("graph", type=Path, nargs="?", help="a g2o (or TORO) file; default: a synthetic helix")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--method", choices=("gn_pcg", "block_sor"), default="gn_pcg")
    ap.add_argument("--robust", action="store_true", help="GNC-TLS on the loop closures")
    ap.add_argument("--max-rounds", type=int, default=500)
    a = ap.parse_args()
    for key, value in main(a.graph, a.robots, a.method, a.robust, a.max_rounds).items():
        print(f"{key:>22}: {value}")
