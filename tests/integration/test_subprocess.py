"""Two OS processes exchange messages over Zenoh (tests/integration/zenoh_peer.py)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration
HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]


def test_two_processes_ping_each_other(port: int) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    endpoint = f"tcp/127.0.0.1:{port}"
    script = str(HERE / "zenoh_peer.py")
    n = 25
    procs = [
        subprocess.Popen([sys.executable, script, "--robot", "0", "--peer", "1", "--listen",
                          endpoint, "--count", str(n), "--last"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env),
        subprocess.Popen([sys.executable, script, "--robot", "1", "--peer", "0", "--connect",
                          endpoint, "--count", str(n)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env),
    ]
    results = []
    try:
        for proc in procs:
            out, err = proc.communicate(timeout=180)
            assert proc.returncode == 0, err
            results.append(json.loads(out.strip().splitlines()[-1]))
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    for res in results:
        assert sorted(res["pings"]) == list(range(n))
        assert sorted(res["pongs"]) == list(range(n))
        assert res["counters"]["sent"]["diag/ping"]["messages"] == 2 * n
        assert res["counters"]["received"]["diag/ping"]["messages"] == 2 * n
        assert res["counters"]["dropped"] == {}
