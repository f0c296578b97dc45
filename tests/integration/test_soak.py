"""The soak benchmark's short variant (benchmarks/soak.py --short): four agent processes, a
router and the observer over two minutes of a looping stream with one agent kill, one router
restart and one partition; nothing may be lost (docs/benchmarks.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration


@pytest.mark.slow
@pytest.mark.long
def test_the_short_soak_loses_nothing(tmp_path: Path) -> None:
    res = subprocess.run([sys.executable, str(REPO / "benchmarks" / "soak.py"), "--json", "--short",
                          "--out", str(tmp_path / "soak")], capture_output=True, text=True, timeout=3600, cwd=REPO)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    fig = json.loads(res.stdout.strip().splitlines()[-1])
    plan = fig["schedule"]
    assert len(plan["kills"]) == len(plan["router_restarts"]) == len(plan["partitions"]) == 1
    done = fig["faults_done"]
    assert len(done["kills"]) == 1 and done["kills"][0]["killed_stream_s"] is not None
    assert len(done["router_restarts"]) == 1 and [e["cut"] for e in done["links"]] == [True, False]
    assert all(t["once_in_order"] for t in fig["trajectories"].values()), fig["trajectories"]
    assert fig["closures"]["lost_at_kills"] == [] and fig["closures"]["accepted_inter"] > 0
    assert fig["checkpoints"]["read"] > 0 and fig["checkpoints"]["unreadable"] == []
    assert fig["team_maps"]["agree"] is True
    assert set(fig["team_maps"]["identical_to_centralised_fusion"].values()) == {1.0}
    assert fig["nothing_lost"] is True
