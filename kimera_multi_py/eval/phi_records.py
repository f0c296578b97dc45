"""PhiRecords: a run's series of φ (the team maps' disagreement), computed off the robots' path.

The run hands over a snapshot of each robot's team-map cells at a record time; :func:`.map_metrics.phi`
runs on it in a worker thread (numpy releases the lock on the large array operations, so on a
second core it overlaps the robots' work), or at once when ``background`` is off. The series is the
same either way: each value depends only on its snapshot (docs/outputs.md, ``map_consensus``).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from kimera_multi_py.eval.map_metrics import Cells, phi

PhiValue = dict[str, float]


def _snapshot(cells: Mapping[int, Cells]) -> dict[int, Cells]:
    """Private copies, so that the maps may change while φ is computed on them."""
    return {r: (np.array(c, copy=True), np.array(rows, copy=True)) for r, (c, rows) in cells.items()}


class PhiRecords:
    """The φ records of one run, in record order: :meth:`record` queues one, :meth:`done` hands back
    those computed so far (each once), :meth:`finish` waits for the rest."""

    def __init__(self, background: bool = True) -> None:
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="phi") if background else None
        self._pending: list[tuple[float, Future[PhiValue]]] = []

    def record(self, t: float, cells: Mapping[int, Cells], pairs: Iterable[tuple[int, int]],
               prior_row: np.ndarray) -> None:
        """φ over ``pairs`` of the robots' ``cells`` at time ``t``."""
        pairs, prior = list(pairs), np.array(prior_row, copy=True)
        job: Future[PhiValue] = Future()
        if self._pool is None:
            job.set_result(phi(cells, pairs, prior))
        else:
            job = self._pool.submit(phi, _snapshot(cells), pairs, prior)
        self._pending.append((t, job))

    def done(self) -> list[tuple[float, PhiValue]]:
        """The records computed so far that were not handed back yet, oldest first (stops at the
        first still running, so the order is kept)."""
        out = []
        while self._pending and self._pending[0][1].done():
            t, job = self._pending.pop(0)
            out.append((t, job.result()))
        return out

    def finish(self) -> list[tuple[float, PhiValue]]:
        """Every record not handed back yet (waiting for those still running); the worker stops."""
        out = [(t, job.result()) for t, job in self._pending]
        self._pending = []
        if self._pool is not None:
            self._pool.shutdown()
        return out
