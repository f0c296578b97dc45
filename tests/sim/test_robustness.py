"""The robustness benchmark's quick sweep (2 seeds x 3 robots on office): team ATE at most half
of dead reckoning's, no robot in an aliased frame, no false closure accepted (issue 11's
targets, on the quick subset)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_quick_robustness_sweep() -> None:
    out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "team_robustness.py"), "--quick", "--json"],
                         capture_output=True, text=True, check=True, timeout=1800)
    data = json.loads(out.stdout)
    runs, summary = data["runs"], data["summary"]
    assert len(runs) == 2 and all("error" not in r for r in runs), [r.get("error") for r in runs]
    assert summary["false_accepted_total"] == 0
    for r in runs:
        assert r["team_ate_m"] <= 0.5 * r["odometry_ate_m"], r
        assert "aliased" not in r["frames"], r
        assert len(r["alignment"]) == r["robots"] and all("status" in a for a in r["alignment"])
