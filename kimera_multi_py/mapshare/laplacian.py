"""The paper's consensus step on evidence: the ``laplacian`` map consensus mode (docs/algorithms/map_consensus.md).

Each robot keeps a state ``e_i`` over world cells: column 0 its averaged support count,
columns 1..K its averaged evidence (fixed-point units, float64). Every round

    e_i <- e_i + dA_i + eps * sum_j a_ij (e_j - e_i),   a_ij = 1 / (1 + max(d_i, d_j))

with ``dA_i`` what the robot's own map evidence changed by since the last round (dynamic
average consensus) and Metropolis-Hastings weights. With synchronous, lossless rounds the sum
of the states is conserved and every state tends to the team mean, so ``N e_i`` tends to the
centralised evidence sum and the team map ``clamp(prior + round(N e_i))`` to the centralised
fusion: asymptotically exact. Stale or lost states bias it (each robot uses the latest state it
has of each neighbour); a full state every ``refresh_every`` rounds repairs lost cells.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms.messages.maps import MapState
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.fusion import union_sorted
from kimera_multi_py.mapshare.roam import sparse_diff


class _Copy:
    __slots__ = ("round", "degree", "codes", "values")

    def __init__(self, k1: int) -> None:
        self.round = -1
        self.degree = 0
        self.codes = np.zeros(0, np.int64)
        self.values = np.zeros((0, k1), np.float64)


class LaplacianState:
    """One robot's evidence-consensus state and its copies of the neighbours' states."""

    def __init__(self, k1: int, epsilon: float = 1.0, refresh_every: int = 10) -> None:
        if not 0.0 < epsilon <= 1.0:
            raise ValueError(f"epsilon must lie in (0, 1], got {epsilon}")
        self.k1 = k1
        self.epsilon = float(epsilon)
        self.refresh_every = max(1, int(refresh_every))
        self.codes = np.zeros(0, np.int64)
        self.values = np.zeros((0, k1), np.float64)
        self._own: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros((0, k1), np.int64))
        self._sent: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros((0, k1), np.float64))
        self.copies: dict[int, _Copy] = {}
        self.round = 0

    def reset(self) -> None:
        """Forget the mixture (the frame changed): the state restarts from the own evidence."""
        self.codes = self._own[0].copy()
        self.values = self._own[1].astype(np.float64)
        self.copies.clear()
        self._sent = (np.zeros(0, np.int64), np.zeros((0, self.k1), np.float64))

    def absorb_own(self, local: SubmapMap) -> None:
        """``e_i += dA_i``: what the robot's own evidence (with support in column 0) changed by."""
        codes, rows, support = local.evidence()
        now = rows.astype(np.int64)
        now[:, 0] = support
        dc, drows = sparse_diff((codes, now), self._own)
        self._own = (codes, now)
        keep = np.any(drows != 0, axis=1)
        self._add(dc[keep], drows[keep].astype(np.float64))

    def handle(self, msg: MapState) -> None:
        if msg.values.shape[1] != self.k1:
            raise MessageError(f"MapState.values: expected {self.k1} columns, got {msg.values.shape[1]}")
        if len(msg.codes) > 1 and np.any(msg.codes[1:] <= msg.codes[:-1]):
            raise MessageError("MapState.codes: must be sorted and unique")
        c = self.copies.setdefault(msg.robot, _Copy(self.k1))
        if msg.round < c.round:
            return  # old (a duplicate of the current round rewrites the same values)
        c.round, c.degree = msg.round, msg.degree
        codes = union_sorted(c.codes, msg.codes)  # cells never disappear: a refresh overwrites all
        values = np.zeros((len(codes), self.k1))
        values[np.searchsorted(codes, c.codes)] = c.values
        values[np.searchsorted(codes, msg.codes)] = msg.values
        c.codes, c.values = codes, values

    def mix(self, neighbours: list[int]) -> None:
        """One consensus step with the neighbours' latest states (Metropolis-Hastings weights).

        ``d_i`` is the number of neighbours (what this robot announces as its degree), so that
        ``a_ij = a_ji`` and the step conserves the sum of the states.
        """
        peers = [j for j in neighbours if j in self.copies]
        if not peers:
            return
        d_i = len(neighbours)
        codes = union_sorted(self.codes, *(self.copies[j].codes for j in peers))
        e = np.zeros((len(codes), self.k1))
        e[np.searchsorted(codes, self.codes)] = self.values
        step = np.zeros_like(e)
        for j in peers:
            c = self.copies[j]
            a = 1.0 / (1.0 + max(d_i, c.degree))
            ej = np.zeros_like(e)
            ej[np.searchsorted(codes, c.codes)] = c.values
            step += a * (ej - e)
        self.codes, self.values = codes, e + self.epsilon * step

    def message(self, robot: int, frame: int, degree: int, max_cells: int = 200_000) -> list[MapState]:
        """The cells changed since the last round (all of them every ``refresh_every`` rounds),
        in messages of at most ``max_cells`` cells."""
        self.round += 1
        full = self.round % self.refresh_every == 0
        if full:
            codes, values = self.codes, self.values
        else:
            sc, sv = self._sent
            pos = np.searchsorted(sc, self.codes).clip(max=max(len(sc) - 1, 0))
            same = np.zeros(len(self.codes), np.bool_)
            if len(sc):
                same = (sc[pos] == self.codes) & np.all(sv[pos] == self.values, axis=1)
            codes, values = self.codes[~same], self.values[~same]
            if len(codes) == 0:
                return []
        self._sent = (self.codes.copy(), self.values.copy())
        step = max(1, int(max_cells))
        return [MapState(robot=robot, round=self.round, frame=frame, degree=degree, full=full,
                         codes=codes[i:i + step].copy(), values=values[i:i + step].copy())
                for i in range(0, len(codes), step)]

    def team_rows(self, team_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``N e_i`` rounded: world codes, evidence rows (column 0 = 0) of live cells, support."""
        scaled = np.rint(team_size * self.values).astype(np.int64)
        live = scaled[:, 0] > 0
        rows = scaled[live]
        support = rows[:, 0].copy()
        rows[:, 0] = 0
        return self.codes[live], rows, support

    def _add(self, codes: np.ndarray, rows: np.ndarray) -> None:
        if len(codes) == 0:
            return
        allc = union_sorted(self.codes, codes)
        out = np.zeros((len(allc), self.k1))
        out[np.searchsorted(allc, self.codes)] = self.values
        out[np.searchsorted(allc, codes)] += rows
        self.codes, self.values = allc, out
