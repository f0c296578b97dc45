"""The single-process team is driven by its simulated clock, not by wall time: a seed gives the
same results however loaded the machine is, and however lossy its links."""

import json
import threading
import time

import pytest

from kimera_multi_py.comms.loopback import Faults
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

from .helpers import TINY, short_tiny


def _burn(stop: threading.Event) -> None:
    while not stop.is_set():
        sum(i * i for i in range(10_000))
        time.sleep(0)


@pytest.mark.slow
def test_distributed_runs_of_one_seed_are_identical_even_under_load():
    first = SimRunner(load_scenario(TINY), seed=1, mode="distributed", map_consensus="off").run().metrics()
    stop = threading.Event()
    burner = threading.Thread(target=_burn, args=(stop,), daemon=True)
    burner.start()
    try:
        second = SimRunner(load_scenario(TINY), seed=1, mode="distributed", map_consensus="off").run().metrics()
    finally:
        stop.set()
        burner.join()
    assert first["pgo_runs"] >= 2 and first["loop_closures"]["verified"] > 0
    assert json.dumps(second, sort_keys=True) == json.dumps(first, sort_keys=True)  # NaN-safe equality


def _lossy(faults: Faults) -> tuple[dict, int]:
    runner = SimRunner(short_tiny(), seed=0, mode="distributed", faults=faults, quality=False)
    metrics = runner.run().metrics()
    return metrics, sum(n.queries_retried for n in runner.nodes)


@pytest.mark.slow
def test_lossy_runs_of_one_seed_are_identical():
    """Lost queries and delayed messages cost simulated time, not wall time: a query's wait ends
    when its reply can no longer arrive, delays run on the network's event time, so two lossy runs
    of one seed give the same results (docs/deployment.md, "Faults on the simulated clock")."""
    faults = Faults(drop=0.2, delay=0.02, jitter=0.01)
    first, retried = _lossy(faults)
    second, _ = _lossy(faults)
    assert retried > 0  # queries were lost and asked again
    assert first["loop_closures"]["verified"] > 0 and first["pgo_runs"] >= 2
    assert json.dumps(second, sort_keys=True) == json.dumps(first, sort_keys=True)  # NaN-safe equality
