"""Map consensus metrics: disagreement, agreement with the centralised fusion, clamping, bytes.

Every function works on *cells*: sorted finest-level Morton codes and their int16 fixed-point
rows (``MapConsensus.team_cells()``, or :func:`~kimera_multi_py.mapshare.fusion.octree_cells` of a tree). A cell a
robot does not know counts as the prior (whose occupancy log-odds is 0, as ROAM counts it).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from kimera_multi_py.mapping.observation import SCALE

Cells = tuple[np.ndarray, np.ndarray]


def occupancy_logodds(h: np.ndarray) -> np.ndarray:
    """``log(P(occupied) / P(free)) = logsumexp(h[1:])`` per row (float log-odds, column 0 = 0)."""
    x = h[:, 1:]
    m = x.max(axis=1, keepdims=True)
    return (m + np.log(np.exp(x - m).sum(axis=1, keepdims=True)))[:, 0]


def _find(codes: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Index into the sorted ``ref`` of each of ``codes``, -1 where it is not there."""
    if len(ref) == 0:
        return np.full(len(codes), -1, np.int64)
    j = np.searchsorted(ref, codes).clip(max=len(ref) - 1)
    return np.where(ref[j] == codes, j, -1)


def _differing(a: Cells, b: Cells, prior: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """The size of the union of two cell sets, and the cells whose rows differ (a cell one side does
    not know counts as ``prior`` there): their positions in the sorted union and both int16 rows."""
    (ca, ra), (cb, rb) = a, b
    if np.array_equal(ca, cb):  # the common case: the same cells, rows differing in few of them
        pos = np.flatnonzero((ra != rb).any(axis=1))
        return len(ca), pos, ra[pos], rb[pos]
    in_b, in_a = _find(ca, cb), _find(cb, ca)
    both = np.flatnonzero(in_b >= 0)
    both = both[(ra[both] != rb[in_b[both]]).any(axis=1)]
    only_a = np.flatnonzero(in_b < 0)
    only_a = only_a[(ra[only_a] != prior).any(axis=1)]
    only_b = np.flatnonzero(in_a < 0)
    only_b = only_b[(rb[only_b] != prior).any(axis=1)]
    codes = np.concatenate([ca[both], ca[only_a], cb[only_b]])
    order = np.argsort(codes)
    rows_a = np.concatenate([ra[both], ra[only_a], np.broadcast_to(prior, (len(only_b), len(prior)))])
    rows_b = np.concatenate([rb[in_b[both]], np.broadcast_to(prior, (len(only_a), len(prior))), rb[only_b]])
    size = len(ca) + len(cb) - int((in_b >= 0).sum())
    return size, (np.searchsorted(ca, codes[order]) + np.searchsorted(cb, codes[order])
                  - np.searchsorted(ca[in_b >= 0], codes[order])), rows_a[order], rows_b[order]


def phi(cells: Mapping[int, Cells], pairs: Iterable[tuple[int, int]], prior_row: np.ndarray) -> dict[str, float]:
    """Disagreement over neighbour pairs: ``sum ||h_i - h_j||^2`` (log-odds vectors), the same per
    cell of the pairs' union, and ROAM's ``sum (l_i - l_j)^2`` on occupancy log-odds.

    Only the cells whose int16 rows differ are converted to floats. The squared differences are
    summed exactly in integers (fixed point), and ROAM's terms are summed over the whole union (zero
    where the rows agree) in the order of a dense computation, so the figures are bit for bit those of
    the dense float arrays over the union of cells."""
    total, roam, n = 0.0, 0.0, 0
    prior = np.asarray(prior_row, dtype=np.int16)
    for i, j in pairs:
        size, pos, ri, rj = _differing(cells[i], cells[j], prior)
        d = ri.astype(np.int64) - rj.astype(np.int64)
        total += int(np.einsum("ij,ij->", d, d)) / SCALE**2
        if size:
            terms = np.zeros(size, np.float64)
            terms[pos] = (occupancy_logodds(ri / SCALE) - occupancy_logodds(rj / SCALE)) ** 2
            roam += float(terms.sum())
        n += size
    return {"phi": total, "phi_per_cell": total / n if n else 0.0, "phi_roam": roam}


def agreement(cells: Cells, reference: Cells) -> dict[str, float]:
    """Over the reference's cells: the fraction whose label (argmax) and whose values are equal."""
    ref_codes, ref_rows = reference
    if len(ref_codes) == 0:
        return {"label": 1.0, "identical": 1.0, "cells": 0}
    codes, rows = cells
    pos = np.searchsorted(codes, ref_codes).clip(max=max(len(codes) - 1, 0))
    known = np.zeros(len(ref_codes), np.bool_)
    if len(codes):
        known = codes[pos] == ref_codes
    mine = rows[pos[known]]
    ref = ref_rows[known]
    label = np.zeros(len(ref_codes), np.bool_)
    same = np.zeros(len(ref_codes), np.bool_)
    label[known] = np.argmax(mine, axis=1) == np.argmax(ref, axis=1)
    same[known] = np.all(mine == ref, axis=1)
    return {"label": float(label.mean()), "identical": float(same.mean()), "cells": int(len(ref_codes))}


def clamped_fraction(cells: Cells, lo: int, hi: int) -> float:
    """The fraction of cells with a class entry at the clamp bound ``lo`` or ``hi`` (fixed point)."""
    rows = cells[1][:, 1:]
    if len(rows) == 0:
        return 0.0
    return float(np.any((rows <= lo) | (rows >= hi), axis=1).mean())


@dataclass
class TeamMapReport:
    """What ``results.json["map_consensus"]`` holds for one mode (see :meth:`to_dict`)."""

    mode: str
    rounds: int
    phi: list[float] = field(default_factory=list)
    phi_per_cell: list[float] = field(default_factory=list)
    phi_roam: list[float] = field(default_factory=list)
    agreement: dict[int, dict[str, float]] = field(default_factory=dict)
    clamped_fraction: dict[int, float] = field(default_factory=dict)
    team_cells: dict[int, int] = field(default_factory=dict)
    bytes: dict[int, dict[str, int]] = field(default_factory=dict)
    roam_bytes: dict[int, int] = field(default_factory=dict)
    bytes_ratio_vs_roam: float = float("nan")

    def record_phi(self, value: Mapping[str, float]) -> None:
        self.phi.append(value["phi"])
        self.phi_per_cell.append(value["phi_per_cell"])
        self.phi_roam.append(value["phi_roam"])

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        for name in ("agreement", "clamped_fraction", "team_cells", "bytes", "roam_bytes"):
            d[name] = {str(k): v for k, v in d[name].items()}
        return d


def team_map_report(
    mode: str,
    rounds: int,
    cells: Mapping[int, Cells],
    reference: Cells,
    clamp: tuple[int, int],
    bytes_sent: Mapping[int, Mapping[str, int]],
    roam_bytes: Mapping[int, int],
    history: TeamMapReport | None = None,
) -> TeamMapReport:
    """The end-of-run report: agreement with ``reference`` (the centralised fusion), clamping,
    bytes and the ratio of all bytes sent to ``roam_bytes`` (what ROAM sends on the same run)."""
    rep = history or TeamMapReport(mode, rounds)
    rep.mode, rep.rounds = mode, rounds
    rep.agreement = {r: agreement(c, reference) for r, c in sorted(cells.items())}
    rep.clamped_fraction = {r: clamped_fraction(c, *clamp) for r, c in sorted(cells.items())}
    rep.team_cells = {r: int(len(c[0])) for r, c in sorted(cells.items())}
    rep.bytes = {r: dict(sorted(b.items())) for r, b in sorted(bytes_sent.items())}
    rep.roam_bytes = dict(sorted(roam_bytes.items()))
    total = sum(sum(b.values()) for b in bytes_sent.values())
    ref = sum(roam_bytes.values())
    rep.bytes_ratio_vs_roam = total / ref if ref else float("nan")
    return rep
