"""Semantic log-odds in fixed point, and the inverse sensor model that turns a scan's cells into
updates (docs/algorithms/mapping.md).

Fixed point
    A cell's log-odds vector ``h`` against the free class has K+1 entries, column 0 (free) the
    pivot and always 0, stored as int16 with ``SCALE`` steps per unit. Fixed point makes every
    update an exact integer addition, so identical evidence gives bit-identical cells (pruning)
    and de-integrating a submap is exact (:mod:`.submaps`).

Observation model (all configurable)
    A cell holding end points of one scan gets ``l = phi_hit + psi * f`` where ``f`` is the
    fraction of its end points per class; a cell a ray passes through gets ``l = miss`` on every
    class. ``phi_hit`` is "occupied, class unknown" spread evenly over the K classes and chosen so
    that a cell at the uniform prior gains exactly ``hit`` in occupancy log-odds.
    ``psi = log(acc (K-1) / (1-acc))`` is the log-likelihood ratio of a label that is right with
    probability ``acc`` (this lets the observed class win and the others fall, so clamped cells
    converge to identical vectors). New cells start at the prior ``-log K`` on every class
    (occupancy probability 0.5). After each update every entry is clamped to ``[h_min, h_max]``.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.mapping.raycast import ScanCells

SCALE = 1024  # fixed-point steps per unit of log-odds
MAX_ABS_LOGODDS = 15.0  # keeps h + l inside int16


def quantise(x: float | np.ndarray) -> np.ndarray:
    """Quantise log-odds to fixed point."""
    return np.round(np.asarray(x, dtype=np.float64) * SCALE).astype(np.int64)


class ObservationModel:
    """Fixed-point inverse sensor model shared by the octree and the submaps."""

    def __init__(
        self,
        num_classes: int,
        hit: float = 0.85,
        miss: float = -0.4,
        psi: float | None = None,
        label_accuracy: float = 0.9,
        h_min: float = -5.0,
        h_max: float = 5.0,
        prior: float | None = None,
    ) -> None:
        if num_classes < 1:
            raise ValueError(f"num_classes must be at least 1, got {num_classes}")
        if not 0.0 < label_accuracy < 1.0:
            raise ValueError(f"label_accuracy must lie in (0, 1), got {label_accuracy}")
        given = {
            "hit": hit,
            "miss": miss,
            "psi": psi,
            "h_min": h_min,
            "h_max": h_max,
            "prior": prior,
        }
        bad = [k for k, v in given.items() if v is not None and not np.isfinite(v)]
        if bad:
            raise ValueError(f"non-finite observation model parameters: {', '.join(bad)}")
        K = int(num_classes)
        if psi is None:
            psi = float(np.log(label_accuracy * max(K - 1, 1) / (1.0 - label_accuracy)))
        if prior is None:
            prior = -float(np.log(K))
        phi = hit - float(np.log((K - 1 + np.exp(psi)) / K))
        if not (-MAX_ABS_LOGODDS <= h_min < 0.0 < h_max <= MAX_ABS_LOGODDS):
            raise ValueError(
                f"need -{MAX_ABS_LOGODDS} <= h_min < 0 < h_max <= {MAX_ABS_LOGODDS}, "
                f"got [{h_min}, {h_max}]"
            )
        if not h_min <= prior <= h_max:
            raise ValueError(f"prior {prior} outside [{h_min}, {h_max}]")
        for name, v in (("miss", miss), ("phi_hit", phi), ("phi_hit + psi", phi + psi)):
            if abs(v) > MAX_ABS_LOGODDS:
                raise ValueError(f"{name} = {v} exceeds {MAX_ABS_LOGODDS} in magnitude")
        if miss >= 0:
            raise ValueError(f"miss must be negative, got {miss}")
        self.num_classes = K
        self.hit, self.miss, self.psi, self.phi = float(hit), float(miss), float(psi), float(phi)
        self.label_accuracy = float(label_accuracy)
        self.h_min, self.h_max, self.prior = float(h_min), float(h_max), float(prior)
        self.lo, self.hi = int(quantise(h_min)), int(quantise(h_max))
        self.miss_row = np.zeros(K + 1, dtype=np.int16)
        self.miss_row[1:] = quantise(miss)
        self.prior_row = np.zeros(K + 1, dtype=np.int16)
        self.prior_row[1:] = quantise(prior)
        # quantised hit rows for every label fraction are built on demand

    def params(self) -> dict[str, float]:
        return {
            "hit": self.hit,
            "miss": self.miss,
            "psi": self.psi,
            "label_accuracy": self.label_accuracy,
            "h_min": self.h_min,
            "h_max": self.h_max,
            "prior": self.prior,
        }

    def hit_rows(self, label_counts: np.ndarray) -> np.ndarray:
        """Update rows ``(m, K+1)`` int16 for cells with these end-point label histograms."""
        counts = np.asarray(label_counts, dtype=np.float64)
        total = counts[:, 1:].sum(axis=1, keepdims=True)
        rows = np.zeros(counts.shape, dtype=np.int16)
        frac = counts[:, 1:] / np.maximum(total, 1.0)
        rows[:, 1:] = quantise(self.phi + self.psi * frac)
        return rows

    def deltas(self, cells: ScanCells) -> tuple[np.ndarray, np.ndarray]:
        """Sorted codes and their update rows ``(m, K+1)`` int16 for one scan's cells."""
        free, occ = cells.free, cells.occupied
        m = len(free) + len(occ)
        at = np.searchsorted(free, occ) + np.arange(len(occ))  # merge two sorted runs
        is_free = np.ones(m, dtype=np.bool_)
        is_free[at] = False
        codes = np.empty(m, dtype=np.int64)
        codes[at] = occ
        codes[is_free] = free
        rows = np.empty((m, self.num_classes + 1), dtype=np.int16)
        rows[:] = self.miss_row
        rows[at] = self.hit_rows(cells.label_counts)
        return codes, rows

    def clamp(self, rows: np.ndarray) -> np.ndarray:
        """Clamp fixed-point rows in place (column 0 stays 0 since ``lo < 0 < hi``)."""
        return np.clip(rows, self.lo, self.hi, out=rows)


def occupied_mask(values: np.ndarray) -> np.ndarray:
    """Rows (fixed point) whose occupancy probability exceeds 0.5: ``logsumexp(h[1:]) > 0``."""
    h = values[:, 1:].astype(np.float64) / SCALE
    hmax = h.max(axis=1) if h.shape[1] else np.zeros(len(h))
    lse = hmax + np.log(np.exp(h - hmax[:, None]).sum(axis=1))
    return lse > 0.0
