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
from kimera_multi_py.mapshare.fusion import union_sorted

Cells = tuple[np.ndarray, np.ndarray]


def _aligned(a: Cells, b: Cells, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    codes = union_sorted(a[0], b[0])
    out = []
    for c, r in (a, b):
        full = np.empty((len(codes), len(prior)), np.float64)
        full[:] = prior
        full[np.searchsorted(codes, c)] = r
        out.append(full / SCALE)
    return out[0], out[1]


def occupancy_logodds(h: np.ndarray) -> np.ndarray:
    """``log(P(occupied) / P(free)) = logsumexp(h[1:])`` per row (float log-odds, column 0 = 0)."""
    x = h[:, 1:]
    m = x.max(axis=1, keepdims=True)
    return (m + np.log(np.exp(x - m).sum(axis=1, keepdims=True)))[:, 0]


def phi(cells: Mapping[int, Cells], pairs: Iterable[tuple[int, int]], prior_row: np.ndarray) -> dict[str, float]:
    """Disagreement over neighbour pairs: ``sum ||h_i - h_j||^2`` (log-odds vectors), the same per
    cell of the pairs' union, and ROAM's ``sum (l_i - l_j)^2`` on occupancy log-odds."""
    total, roam, n = 0.0, 0.0, 0
    prior = np.asarray(prior_row, dtype=np.float64)
    for i, j in pairs:
        hi, hj = _aligned(cells[i], cells[j], prior)
        total += float(((hi - hj) ** 2).sum())
        roam += float(((occupancy_logodds(hi) - occupancy_logodds(hj)) ** 2).sum()) if len(hi) else 0.0
        n += len(hi)
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
