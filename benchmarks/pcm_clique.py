"""PCM's maximum clique: igraph (what the agents use) against networkx's exact search, on the
consistency graphs of a real team run.

    python benchmarks/pcm_clique.py --json [--scenario sims/aliased_wing.toml] [--robots 3] [--seed 9]

One single-process simulation runs (distributed mode, map consensus off) and every consistency
graph PCM searches is recorded. Each graph is then searched again by both libraries, timed, and
the clique sizes compared (both searches are exact, so the sizes must agree; a tie may be broken
differently). The reference is networkx's ``max_weight_clique``, measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import networkx as nx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from kimera_multi_py.core.clique import max_clique  # noqa: E402
from kimera_multi_py.frontend import pcm as pcm_module  # noqa: E402


def record_graphs(scenario: str, robots: int, seed: int) -> list[np.ndarray]:
    """The adjacency matrices PCM searched during one distributed run."""
    from kimera_multi_py.sim import load_scenario
    from kimera_multi_py.workflow.simulate import SimRunner

    graphs: list[np.ndarray] = []
    original = pcm_module.max_clique

    def recording(adj: np.ndarray, cost: np.ndarray | None = None) -> np.ndarray:
        graphs.append(np.array(adj, dtype=bool))
        return original(adj, cost)

    pcm_module.max_clique = recording  # type: ignore[assignment]
    try:
        cfg = load_scenario(scenario, robots=robots)
        with tempfile.TemporaryDirectory() as d:
            SimRunner(cfg, seed=seed, mode="distributed", out_dir=d, map_consensus="off", quality=False).run()
    finally:
        pcm_module.max_clique = original  # type: ignore[assignment]
    return graphs


def compare(graphs: list[np.ndarray]) -> dict[str, Any]:
    t_ig = t_nx = 0.0
    mismatched = 0
    for adj in graphs:
        t = time.perf_counter()
        ours = max_clique(adj)
        t_ig += time.perf_counter() - t
        t = time.perf_counter()
        g = nx.Graph()
        g.add_nodes_from(range(len(adj)))
        g.add_edges_from(zip(*np.nonzero(np.triu(adj, k=1)), strict=True))
        ref, _ = nx.max_weight_clique(g, weight=None)
        t_nx += time.perf_counter() - t
        mismatched += len(ours) != len(ref)
    sizes = [len(a) for a in graphs]
    return {"graphs": len(graphs), "max_nodes": max(sizes, default=0), "mean_nodes": float(np.mean(sizes or [0])),
            "igraph_s": t_ig, "networkx_s": t_nx, "speedup": t_nx / max(t_ig, 1e-12),
            "size_mismatches": mismatched}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default=str(REPO / "sims" / "aliased_wing.toml"))
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--seed", type=int, default=9)
    ap.add_argument("--json", action="store_true", help="print the JSON only")
    args = ap.parse_args()
    out = {"scenario": Path(args.scenario).stem, "robots": args.robots, "seed": args.seed,
           **compare(record_graphs(args.scenario, args.robots, args.seed))}
    if args.json:
        print(json.dumps(out, indent=1))
    else:
        print(f"{out['graphs']} PCM graphs (up to {out['max_nodes']} closures): igraph {out['igraph_s']:.2f} s, "
              f"networkx {out['networkx_s']:.2f} s ({out['speedup']:.0f}x), {out['size_mismatches']} size mismatches")


if __name__ == "__main__":
    main()
