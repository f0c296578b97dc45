"""The robustness benchmark: its quick sweep (2 generated buildings x 3 robots, distributed, the
default team map on) meets the safety targets, and its report and resume work on recorded runs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.slow
@pytest.mark.long
def test_quick_robustness_sweep() -> None:
    out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "team_robustness.py"), "--quick", "--json"],
                         capture_output=True, text=True, check=True, timeout=3600)
    data = json.loads(out.stdout)
    runs, summary = data["runs"], data["summary"]
    assert len(runs) == 2 and all("error" not in r for r in runs), [r.get("error") for r in runs]
    assert {r["scenario"] for r in runs} == {"gen0", "gen1"} and all(r["team_map"] == "exact" for r in runs)
    assert summary["false_accepted_total"] == 0
    for r in runs:
        assert r["team_ate_m"] <= 0.5 * r["odometry_ate_m"], r
        assert r["team_ate_m"] <= r["registration_ate_m"], r  # never worse than the robots' own scan odometry
        assert "aliased" not in r["frames"], r
        assert len(r["alignment"]) == r["robots"] and all("status" in a for a in r["alignment"])
    kept_out = {(k["scenario"], k["robot"]) for k in summary["kept_out"]}
    assert kept_out == {(r["scenario"], i) for r in runs for i, f in enumerate(r["frames"]) if f == "excluded"}


def test_report_takes_each_run_from_the_latest_listed_code(tmp_path: Path) -> None:
    """``--report`` runs nothing: one row per (scenario, robots, seed, mode), a later label's run
    replacing an earlier one's; runs on unlisted code are left out, and the summary says which
    code each mode's runs stand on."""
    def run(mode: str, seed: int, code: str, ate: float) -> dict[str, object]:
        zero = {f"{k}_{t}_{s}": 0 for k in ("inter", "intra") for t in ("true", "false")
                for s in ("verified", "rejected_pcm", "rejected_gnc", "accepted")}
        return {"scenario": "office", "robots": 3, "seed": seed, "mode": mode, "team_ate_m": ate,
                "odometry_ate_m": 0.4, "ratio": ate / 0.4, "frames": ["true"] * 3, "alignment": [],
                "closures": zero, "wall_s": 1.0, "code": code}

    f = tmp_path / "runs.jsonl"
    rows = [run("centralized", 0, "old-x", 0.030), run("distributed", 0, "old-x", 0.090),
            run("distributed", 0, "new-x", 0.031), run("distributed", 1, "other-x", 0.5),
            run("centralized", 1, "old-x", 0.020), run("distributed", 1, "new-x", 0.025)]
    f.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "team_robustness.py"), "--report", str(f),
                          "--codes", "old", "new", "--modes", "distributed", "centralized", "--seeds", "0", "1",
                          "--json"], capture_output=True, text=True, check=True, timeout=120)
    data = json.loads(out.stdout)
    got = {(r["mode"], r["seed"]): (r["code"], r["team_ate_m"]) for r in data["runs"]}
    assert got == {("centralized", 0): ("old-x", 0.030), ("centralized", 1): ("old-x", 0.020),
                   ("distributed", 0): ("new-x", 0.031), ("distributed", 1): ("new-x", 0.025)}
    assert data["codes"] == {"centralized": {"old-x": 2}, "distributed": {"new-x": 2}}
    pairs = {p["seed"]: p["ok"] for p in data["summary"]["distributed_vs_centralized"]}
    assert pairs == {0: True, 1: False}  # 0.031 <= 1.05 x 0.030; 0.025 > 1.05 x 0.020


@pytest.mark.parametrize("content", ["not json\n", '{"scenario": "office"}\n', "[1, 2]\n"])
def test_report_names_a_bad_line(tmp_path: Path, content: str) -> None:
    f = tmp_path / "runs.jsonl"
    f.write_text(content)
    out = subprocess.run([sys.executable, str(REPO / "benchmarks" / "team_robustness.py"), "--report", str(f)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 1
    assert out.stderr.strip().splitlines() == [out.stderr.strip()] and "line 1: not a run record" in out.stderr
