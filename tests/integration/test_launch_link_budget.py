"""``launch --link-budget``: two agent processes over real Zenoh on 127.0.0.1, each pacing its
puts, queries and replies through a token bucket; the run's results.json gathers their links."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.sim.helpers import short_tiny_file

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_launch_with_a_link_budget(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", "launch", str(short_tiny_file(tmp_path)),
                           "--robots", "2", "--seed", "0", "--out", str(out), "--rate", "4", "--link-budget", "50"],
                          capture_output=True, text=True, timeout=900, cwd=REPO)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    res = json.loads((out / "results.json").read_text())
    lb = res["link_budget"]
    assert lb["kbps"] == 50 and lb["policy"] == "priority"
    assert set(lb["links"]) == {"0->*", "1->*"}
    for r in (0, 1):
        link = lb["links"][f"{r}->*"]
        # every payload the robot counted as sent crossed its budgeted link
        traffic = json.loads((out / f"robot{r}" / "traffic.json").read_text())
        sent = sum(v["bytes"] for v in traffic["counters"]["sent"].values())
        assert link["bytes"] == sent > 0
        assert 0 < link["queue_delay_mean_s"] <= link["queue_delay_max_s"]
        assert "link_budget: 50" in (out / f"robot{r}" / "config.yaml").read_text()
    assert res["loop_closures"]["false_accepted_inter"] == 0 and res["pgo_runs"] >= 1
