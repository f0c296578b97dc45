"""φ (team maps' disagreement) against the dense formula it replaced, on random cell sets."""

from __future__ import annotations

import numpy as np
import pytest

from kimera_multi_py.eval.map_metrics import Cells, phi
from kimera_multi_py.mapping.observation import SCALE

K1 = 13  # free + 12 classes, as the agents' maps


def _aligned_dense(a: Cells, b: Cells, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The reference: both sides as float64 rows over the union of cells (prior where unknown)."""
    codes = np.union1d(a[0], b[0])
    out = []
    for c, r in (a, b):
        full = np.empty((len(codes), len(prior)), np.float64)
        full[:] = prior
        full[np.searchsorted(codes, c)] = r
        out.append(full / SCALE)
    return out[0], out[1]


def _occupancy_dense(h: np.ndarray) -> np.ndarray:
    x = h[:, 1:]
    m = x.max(axis=1, keepdims=True)
    return (m + np.log(np.exp(x - m).sum(axis=1, keepdims=True)))[:, 0]


def phi_dense(cells: dict[int, Cells], pairs: list[tuple[int, int]], prior_row: np.ndarray) -> dict[str, float]:
    """The formula φ had before it skipped the cells both sides agree on (kept as the reference)."""
    total, roam, n = 0.0, 0.0, 0
    prior = np.asarray(prior_row, dtype=np.float64)
    for i, j in pairs:
        hi, hj = _aligned_dense(cells[i], cells[j], prior)
        total += float(((hi - hj) ** 2).sum())
        roam += float(((_occupancy_dense(hi) - _occupancy_dense(hj)) ** 2).sum()) if len(hi) else 0.0
        n += len(hi)
    return {"phi": total, "phi_per_cell": total / n if n else 0.0, "phi_roam": roam}


def _prior() -> np.ndarray:
    p = np.full(K1, -2300, np.int16)
    p[0] = 0
    return p


def _team(rng: np.random.Generator, robots: int, universe: int, same_cells: bool, p_diff: float,
          prior: np.ndarray) -> dict[int, Cells]:
    """Robots' cells drawn from one base map: some cells dropped, some rows changed, some at the prior."""
    base_codes = np.sort(rng.choice(10 * universe + 1, size=universe, replace=False)).astype(np.int64)
    base_rows = rng.integers(-8000, 8000, size=(universe, K1)).astype(np.int16)
    base_rows[:, 0] = 0
    base_rows[rng.random(universe) < 0.1] = prior
    out = {}
    for r in range(robots):
        keep = np.ones(universe, np.bool_) if same_cells else rng.random(universe) < rng.uniform(0.3, 1.0)
        rows = base_rows[keep].copy()
        change = rng.random(len(rows)) < p_diff
        rows[change, 1:] += rng.integers(-600, 600, size=(int(change.sum()), K1 - 1)).astype(np.int16)
        rows[change & (rng.random(len(rows)) < 0.2)] = prior  # a cell one side knows only at the prior
        out[r] = (base_codes[keep], rows)
    return out


@pytest.mark.parametrize("seed", range(12))
def test_phi_equals_the_dense_formula_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    prior = _prior()
    robots = int(rng.integers(2, 5))
    cells = _team(rng, robots, int(rng.integers(1, 3000)), same_cells=bool(seed % 3 == 0),
                  p_diff=float(rng.choice([0.0, 0.01, 0.3, 1.0])), prior=prior)
    pairs = [(a, b) for a in range(robots) for b in range(a + 1, robots)]
    got, want = phi(cells, pairs, prior), phi_dense(cells, pairs, prior)
    assert got == want  # exact: the same floats, not merely close


def test_phi_on_empty_and_disjoint_maps() -> None:
    prior = _prior()
    empty: Cells = (np.zeros(0, np.int64), np.zeros((0, K1), np.int16))
    rows = np.arange(3 * K1, dtype=np.int16).reshape(3, K1) * 100
    rows[:, 0] = 0
    some: Cells = (np.array([2, 5, 9], np.int64), rows)
    other: Cells = (np.array([1, 6], np.int64), rows[:2] - 50)
    cells = {0: empty, 1: empty, 2: some, 3: other}
    for pairs in ([(0, 1)], [(0, 2)], [(2, 0)], [(2, 3)], [(0, 1), (2, 3), (3, 2), (1, 3)]):
        assert phi(cells, pairs, prior) == phi_dense(cells, pairs, prior)
    assert phi(cells, [(0, 1)], prior) == {"phi": 0.0, "phi_per_cell": 0.0, "phi_roam": 0.0}
    assert phi(cells, [(2, 2)], prior)["phi"] == 0.0
    assert phi(cells, [(2, 3)], prior)["phi"] > 0.0
