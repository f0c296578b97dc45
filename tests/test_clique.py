"""The exact maximum clique (igraph) against networkx's exact search, and its tie-break."""

from __future__ import annotations

import networkx as nx
import numpy as np
import pytest

from kimera_multi_py.core.clique import max_clique


def _random_adj(rng: np.random.Generator, n: int, p: float) -> np.ndarray:
    a = np.triu(rng.random((n, n)) < p, k=1)
    return a | a.T


@pytest.mark.parametrize("seed", range(20))
def test_the_clique_is_a_maximum_clique(seed: int) -> None:
    rng = np.random.default_rng(seed)
    adj = _random_adj(rng, int(rng.integers(1, 40)), float(rng.uniform(0.1, 0.7)))
    c = max_clique(adj)
    assert np.all(adj[np.ix_(c, c)] | np.eye(len(c), dtype=bool))  # a clique
    g = nx.from_numpy_array(adj.astype(int))
    best, _ = nx.max_weight_clique(g, weight=None)
    assert len(c) == len(best)  # and none is larger


def test_ties_go_to_the_smallest_total_cost_then_the_lowest_indices() -> None:
    # two disjoint triangles {0,1,2} and {3,4,5}
    adj = np.zeros((6, 6), dtype=bool)
    for tri in ([0, 1, 2], [3, 4, 5]):
        adj[np.ix_(tri, tri)] = True
    np.fill_diagonal(adj, False)
    assert max_clique(adj).tolist() == [0, 1, 2]
    cost = np.ones((6, 6))
    cost[np.ix_([3, 4, 5], [3, 4, 5])] = 0.5
    assert max_clique(adj, cost).tolist() == [3, 4, 5]
    assert max_clique(adj, np.ones((6, 6))).tolist() == [0, 1, 2]


def test_empty_and_malformed_inputs() -> None:
    assert max_clique(np.zeros((0, 0), dtype=bool)).tolist() == []
    assert max_clique(np.zeros((3, 3), dtype=bool)).tolist() == [0]
    with pytest.raises(ValueError, match="square"):
        max_clique(np.zeros((2, 3), dtype=bool))
