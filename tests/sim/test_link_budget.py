"""The simulation under a link budget: the loopback links run on the simulated clock, so a
budgeted run is as deterministic as any other, and results.json says what each link carried."""

import json
import re

import pytest

from kimera_multi_py.team.config import KimeraConfig
from kimera_multi_py.workflow.simulate import SimRunner

from .helpers import short_tiny


def budgeted(kbps: float, policy: str = "priority") -> dict:
    config = KimeraConfig.defaults().updated({"node": {"link_budget": kbps, "link_policy": policy}})
    return SimRunner(short_tiny(), seed=0, mode="distributed", quality=False, config=config).run().metrics()


@pytest.mark.slow
def test_budgeted_run_is_deterministic_and_reports_its_links():
    first, second = budgeted(20), budgeted(20)
    assert json.dumps(second, sort_keys=True) == json.dumps(first, sort_keys=True)  # NaN-safe equality
    lb = first["link_budget"]
    assert lb["kbps"] == 20 and lb["policy"] == "priority"
    assert set(lb["links"]) == {"0->1", "1->0"}
    sent = sum(v["bytes"] for v in lb["links"].values())
    # every byte a robot sent crossed its one link (or could not be sent, and is counted as such)
    lost = sum(v["dropped_bytes"] + v["queued_bytes"] for v in lb["links"].values())
    assert sent + lost == first["bytes_sent"]["total"]
    for link in lb["links"].values():
        assert link["messages"] > 0 and 0 < link["queue_delay_mean_s"] <= link["queue_delay_max_s"]
        # every class that crossed the link reports its delay; which class waited longest is not
        # an invariant (a control message waits behind a transfer in progress and behind other
        # control traffic, and little map evidence travels at all): that PGO is never starved by
        # map traffic is the scheduler's test (tests/comms/test_link_budget.py, against FIFO)
        by_class = link["queue_delay_max_s_by_class"]
        assert set(by_class) >= {"control", "map"} and all(v >= 0.0 for v in by_class.values())
    # 20 kB/s: the maps need time after the streams' end, and they get whole
    assert lb["team_maps_complete_s"] is not None and lb["team_maps_complete_s"] > 5.0
    assert all(a["identical"] == 1.0 for a in first["map_consensus"]["agreement"].values())
    assert first["loop_closures"]["true_accepted_inter"] > 0 and first["loop_closures"]["false_accepted_inter"] == 0


def test_the_budget_is_part_of_the_run_configuration(tmp_path):
    config = KimeraConfig.defaults().updated({"node": {"link_budget": 50}})
    runner = SimRunner(short_tiny(), seed=0, mode="distributed", config=config)
    assert runner.links.budget is not None and runner.links.budget.rate == 50_000
    runner.resolved_config().write(tmp_path)
    text = (tmp_path / "config.yaml").read_text()
    assert re.search(r"^\s+link_budget: 50(\.0)?$", text, re.M)
    assert SimRunner(short_tiny(), seed=0, mode="distributed").links.budget is None  # off by default
