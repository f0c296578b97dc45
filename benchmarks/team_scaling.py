"""How the team scales: the distributed simulation with 2, 4 and 8 robots on one scenario.

    python benchmarks/team_scaling.py --json                  # office, seed 0, 2/4/8 robots
    python benchmarks/team_scaling.py --robots 2 4 --scenario sims/small.toml

Each team size runs in a fresh process (so peak RSS is that run's). Per size it reports bytes
per robot per sim-second, the realtime factor (sim seconds per wall second), team ATE, peak RSS
and PGO epochs; the smallest team is the reference the others are compared with in the same run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, resource, sys, tempfile
sys.path.insert(0, {repo!r})
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner
cfg = load_scenario({scenario!r}, robots={robots})
with tempfile.TemporaryDirectory() as d:
    res = SimRunner(cfg, seed={seed}, mode={mode!r}, out_dir=d, map_consensus={map_consensus!r}).run().to_dict()
n = len(res["robots"])
print(json.dumps({{
    "robots": n, "keyframes": res["team"]["keyframes"], "sim_seconds": res["sim_seconds"],
    "wall_s": res["wall_s"], "realtime_factor": res["realtime_factor"],
    "team_ate_m": res["team"]["ate_rmse_m"],
    "bytes_total": res["bytes_sent"]["total"],
    "bytes_per_robot_per_sim_s": res["bytes_sent"]["total"] / n / res["sim_seconds"],
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "pgo_epochs": res["pgo_runs"],
    "false_accepted_inter": res["loop_closures"]["false_accepted_inter"],
    "true_accepted_inter": res["loop_closures"]["true_accepted_inter"],
}}))
"""


def run_one(scenario: str, robots: int, seed: int, mode: str, map_consensus: str) -> dict:
    code = _CHILD.format(repo=str(REPO), scenario=scenario, robots=robots, seed=seed, mode=mode,
                         map_consensus=map_consensus)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mode", default="distributed")
    ap.add_argument("--map-consensus", default="exact", help="off, roam, exact or laplacian")
    ap.add_argument("--json", action="store_true", help="print the JSON summary only")
    args = ap.parse_args()
    runs = []
    for n in sorted(args.robots):
        runs.append(run_one(args.scenario, n, args.seed, args.mode, args.map_consensus))
        print(json.dumps(runs[-1]), file=sys.stderr, flush=True)  # progress: one run per line
    ref = runs[0]
    for r in runs:
        r["vs_smallest"] = {
            "bytes_per_robot_per_sim_s": r["bytes_per_robot_per_sim_s"] / ref["bytes_per_robot_per_sim_s"],
            "realtime_factor": r["realtime_factor"] / ref["realtime_factor"],
            "peak_rss": r["peak_rss_mb"] / ref["peak_rss_mb"],
        }
    summary = {"scenario": Path(args.scenario).name, "seed": args.seed, "mode": args.mode,
               "map_consensus": args.map_consensus, "runs": runs}
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    print(f"{'robots':>6} {'B/robot/s':>10} {'RTF':>6} {'ATE [m]':>8} {'RSS [MB]':>9} {'epochs':>6}")
    for r in runs:
        print(f"{r['robots']:>6} {r['bytes_per_robot_per_sim_s']:>10.0f} {r['realtime_factor']:>6.2f} "
              f"{r['team_ate_m']:>8.3f} {r['peak_rss_mb']:>9.0f} {r['pgo_epochs']:>6}")


if __name__ == "__main__":
    main()
