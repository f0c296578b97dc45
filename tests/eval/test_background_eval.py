"""PhiRecords: φ in a worker thread gives the series computed at once, on the snapshot of each record."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kimera_multi_py.eval.map_metrics import phi
from kimera_multi_py.eval.phi_records import PhiRecords
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

from ..sim.helpers import TINY


def _cells(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    codes = np.sort(rng.choice(5 * n, n, replace=False)).astype(np.int64)
    rows = rng.integers(-3000, 3000, (n, 13)).astype(np.int16)
    rows[:, 0] = 0
    return codes, rows


@pytest.mark.parametrize("background", [True, False])
def test_records_keep_their_order_and_the_values_of_their_snapshots(background: bool) -> None:
    rng = np.random.default_rng(0)
    prior = np.zeros(13, np.int16)
    recs = PhiRecords(background)
    want, got = [], []
    team = {r: _cells(rng, 2000) for r in range(3)}
    for step in range(6):
        pairs = [(0, 1), (0, 2), (1, 2)][: 1 + step % 3]
        want.append((float(step), phi(team, pairs, prior)))
        recs.record(float(step), team, pairs, prior)
        got += recs.done()
        for _, rows in team.values():  # the maps change in place after the record
            rows[rng.random(len(rows)) < 0.2, 1:] += 7
    got += recs.finish()
    assert got == want
    assert recs.done() == [] and recs.finish() == []


@pytest.mark.slow
def test_a_run_gives_the_same_results_with_its_evaluation_in_the_background_or_at_once() -> None:
    """φ in a worker thread and the accuracy team maps in a worker process from the stream's end,
    or both at once in the run's own thread."""
    results = []
    for background in (True, False):
        runner = SimRunner(load_scenario(TINY), seed=0, mode="distributed")
        runner.phi_background = background
        runner.eval_workers = 1 if background else 0
        results.append(runner.run().metrics())
    assert len(results[0]["map_consensus"]["phi"]) >= 3
    assert json.dumps(results[0], sort_keys=True) == json.dumps(results[1], sort_keys=True)  # NaN-safe
