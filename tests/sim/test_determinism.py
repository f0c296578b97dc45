"""The single-process team is driven by its simulated clock, not by wall time: a seed gives the
same results however loaded the machine is."""

import json
import threading
import time

import pytest

from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

from .helpers import TINY


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
