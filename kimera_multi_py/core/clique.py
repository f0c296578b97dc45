"""Maximum cliques of a consistency graph (exact, igraph's C implementation).

PCM (inter- and intra-robot closures) and the object-constellation verifier both accept the
largest set of mutually consistent measurements. The search is exact, and a tie between
equally large cliques is broken by the smallest total pairwise cost (the most mutually
consistent set), then by the lowest indices: the answer does not depend on the search order.
"""

from __future__ import annotations

import sys
from types import ModuleType

import numpy as np


def _import_igraph() -> ModuleType:
    """igraph without its plotting back end. On import, igraph's drawing package imports
    ``matplotlib.pyplot`` whenever matplotlib is installed (in every process; what that costs:
    docs/performance.md), and nothing here draws: while igraph loads, ``import matplotlib``
    fails, so igraph keeps its stand-in, and matplotlib stays importable after."""
    hide = "matplotlib" not in sys.modules
    if hide:
        sys.modules["matplotlib"] = None  # type: ignore[assignment]  # makes `import matplotlib` raise ImportError
    try:
        import igraph
    finally:
        if hide:
            del sys.modules["matplotlib"]
    return igraph


igraph = _import_igraph()


def max_clique(adj: np.ndarray, cost: np.ndarray | None = None) -> np.ndarray:
    """Sorted indices of a maximum clique of the symmetric boolean adjacency ``adj (n, n)``.

    ``cost (n, n)``: pairwise costs for breaking ties (the clique with the smallest sum over its
    pairs wins); without it ties go to the lexicographically smallest index set.
    """
    adj = np.asarray(adj, dtype=bool)
    n = len(adj)
    if adj.shape != (n, n):
        raise ValueError(f"adjacency must be square, got shape {adj.shape}")
    if n == 0:
        return np.zeros(0, dtype=int)
    i, j = np.nonzero(np.triu(adj | adj.T, k=1))
    g = igraph.Graph(n=n, edges=np.column_stack([i, j]).tolist())
    cliques = [np.array(sorted(c), dtype=int) for c in g.largest_cliques()]
    if len(cliques) == 1:
        return cliques[0]
    cliques.sort(key=lambda c: c.tolist())
    if cost is None:
        return cliques[0]
    cost = np.asarray(cost, dtype=float)
    totals = [float(cost[np.ix_(c, c)].sum()) for c in cliques]
    return cliques[int(np.argmin(totals))]  # argmin keeps the first (smallest indices) of equal totals
