"""Wall time of ``kimera-multi sim`` on the tiny scenario, against the same run in-process.

The command is the one ``tests/test_cli.py`` runs (odometry mode, Rerun recording on). The
reference is ``SimRunner(...).run()`` on the same scenario and seed in this process, so the
difference is the CLI's own cost (interpreter start, imports, the recording, the table). The
target is the whole command within 30 s (it was a unit-test threshold before).

    python benchmarks/cli_sim.py --json
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner

REPO = Path(__file__).resolve().parents[1]
EXE = Path(sys.executable).parent / "kimera-multi"
TARGET_S = 30.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true", help="print JSON only")
    ap.add_argument("--scenario", default="sims/tiny.toml")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        proc = subprocess.run([str(EXE), "sim", args.scenario, "--robots", "2", "--seed", "1", "--mode",
                               "odometry", "--out", str(Path(tmp) / "cli"), "--rerun"],
                              capture_output=True, text=True, cwd=REPO, timeout=600)
        cli_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        SimRunner(load_scenario(REPO / args.scenario, robots=2), seed=1, mode="odometry",
                  out_dir=Path(tmp) / "ref").run()
        ref_s = time.perf_counter() - t0
    result = {"scenario": args.scenario, "exit_code": proc.returncode, "cli_wall_s": round(cli_s, 2),
              "reference_in_process_s": round(ref_s, 2), "cli_overhead_s": round(cli_s - ref_s, 2),
              "target_s": TARGET_S, "meets_target": proc.returncode == 0 and cli_s <= TARGET_S}
    print(json.dumps(result) if args.json else json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
