"""Speed and memory of the product as users run it: default settings, team map on.

    python benchmarks/speed.py --json                          # office 3 robots: team map on and off
    python benchmarks/speed.py --cases office3 office3-cent office8 office8-off launch3 --json
    python benchmarks/speed.py --stages --json                 # also a cProfile breakdown by stage
    python benchmarks/speed.py --repo ../other-checkout --json # the same cases on another checkout

Every case runs in a fresh process (so its peak RSS is its own). A simulation case reports the
realtime factor (stream seconds per wall second, the scoring after the run included), CPU
seconds per robot per stream-second (the run's process; ``cpu_s_workers``: the evaluation's
worker processes, which build the quality maps beside it), the process's peak RSS (all robots,
one process) and per robot, ATE and closures (so a faster run that is worse shows it).
``launch3`` starts the router and 3 agent processes at ``--rate 1`` and reports each agent's
CPU seconds per stream-second and peak RSS (the agents write them to ``resources.json``).
With ``--stages`` each simulation runs under cProfile and the cumulative seconds of the stage
functions are reported (profiled time: slower than the plain run, and
nested stages overlap, e.g. frame decisions sit inside PGO).

Targets (docs/performance.md): 3 robots realtime factor >= 5, 8 robots >= 1.5; launch agents
<= 0.2 CPU-s per stream-second and <= 400 MB; 8-robot per-robot peak <= 1.5 x the 3-robot one.
The first case is the reference the others are compared with, measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CASES: dict[str, dict[str, object]] = {
    "office3": {"robots": 3, "mode": "distributed", "map_consensus": "exact"},
    "office3-off": {"robots": 3, "mode": "distributed", "map_consensus": "off"},
    "office3-cent": {"robots": 3, "mode": "centralized", "map_consensus": "exact"},
    "office3-cent-off": {"robots": 3, "mode": "centralized", "map_consensus": "off"},
    "office8": {"robots": 8, "mode": "distributed", "map_consensus": "exact"},
    "office8-off": {"robots": 8, "mode": "distributed", "map_consensus": "off"},
    "office8-cent": {"robots": 8, "mode": "centralized", "map_consensus": "exact"},
    "launch3": {"robots": 3, "launch": True},
}

# stage -> the functions (file:function, as cProfile names them) whose cumulative time it is
STAGES: dict[str, tuple[str, ...]] = {
    "registration": ("scan_odometry.py:step",),
    "map_upkeep": ("submaps.py:integrate", "submaps.py:move_submap", "submaps.py:_flush"),
    "objects": ("objects.py:update", "objects.py:merge_fragments"),
    "people": ("tracking.py:update",),
    "front_end_closures": ("agent.py:_revisits", "agent.py:_intra_closures", "agent.py:_constellation",
                           "node.py:_dispatch_closure"),
    "team_map_fusion": ("consensus.py:step", "consensus.py:handle"),
    "pgo": ("team.py:tick",),
    "frame_decisions": ("frame_decision.py:try_align", "frame_decision.py:screen", "node.py:_safety_net"),
    "scene_graph": ("graph.py:build_scene_graph",),
    "evaluation": ("simulate.py:_evaluate", "simulate.py:_record_phi"),
    "simulator": ("world.py:cast_rays",),
}

_SIM = r"""
import cProfile, json, pstats, resource, sys, tempfile, time
sys.path.insert(0, {repo!r})
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.workflow.simulate import SimRunner
cfg = load_scenario({scenario!r}, robots={robots})
prof = cProfile.Profile() if {stages!r} else None
with tempfile.TemporaryDirectory() as d:
    runner = SimRunner(cfg, seed={seed}, mode={mode!r}, out_dir=d, map_consensus={map_consensus!r})
    t0 = time.perf_counter()
    if prof is not None:
        prof.enable()
    res = runner.run().to_dict()
    if prof is not None:
        prof.disable()
    wall = time.perf_counter() - t0
ru = resource.getrusage(resource.RUSAGE_SELF)
kids = resource.getrusage(resource.RUSAGE_CHILDREN)  # evaluation's worker processes
stages = {{}}
if prof is not None:
    st = pstats.Stats(prof).stats
    for stage, names in {stage_map!r}.items():
        stages[stage] = round(sum(v[3] for (f, _, fn), v in st.items()
                                  if any(f.endswith("/" + n.split(":")[0]) and fn == n.split(":")[1]
                                         for n in names)), 2)
n = len(res["robots"])
lc = res["loop_closures"]
print(json.dumps({{
    "robots": n, "sim_seconds": res["sim_seconds"], "wall_s": round(wall, 1),
    "run_wall_s": res["wall_s"], "realtime_factor": round(res["sim_seconds"] / wall, 3),
    "cpu_s": round(ru.ru_utime + ru.ru_stime, 1),
    "cpu_s_workers": round(kids.ru_utime + kids.ru_stime, 1),
    "cpu_s_per_robot_per_stream_s": round((ru.ru_utime + ru.ru_stime) / n / res["sim_seconds"], 3),
    "peak_rss_mb": round(ru.ru_maxrss / 1024), "peak_rss_mb_per_robot": round(ru.ru_maxrss / 1024 / n),
    "team_ate_m": res["team"]["ate_rmse_m"], "true_inter": lc.get("true_accepted_inter"),
    "false_inter": lc.get("false_accepted_inter"), "phi_records_s": res.get("phi_records_s"),
    "bytes_sent": res["bytes_sent"]["total"], "memory": res.get("memory"),
    "stages_cprofile_s": stages,
}}))
"""


def run_sim(repo: Path, scenario: str, seed: int, robots: int, mode: str, map_consensus: str,
            stages: bool) -> dict:
    code = _SIM.format(repo=str(repo), scenario=scenario, robots=robots, seed=seed, mode=mode,
                       map_consensus=map_consensus, stages=stages, stage_map=STAGES)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(repo))
    if out.returncode:
        return {"failed": out.stderr.strip().splitlines()[-1:] or ["exit code " + str(out.returncode)]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def run_launch(repo: Path, scenario: str, seed: int, robots: int) -> dict:
    """``launch`` at real time; each agent's CPU and peak RSS from its ``resources.json``."""
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", "launch", scenario,
                              "--robots", str(robots), "--seed", str(seed), "--rate", "1", "--out", d],
                             capture_output=True, text=True, cwd=str(repo),
                             env={"PYTHONPATH": str(repo), "PATH": "/usr/bin:/bin"})
        wall = time.perf_counter() - t0
        if out.returncode:
            return {"failed": out.stderr.strip().splitlines()[-1:] or ["exit code " + str(out.returncode)]}
        agents = {}
        for r in range(robots):
            p = Path(d) / f"robot{r}" / "resources.json"
            agents[str(r)] = json.loads(p.read_text()) if p.exists() else None
        res = json.loads((Path(d) / "results.json").read_text())
    ok = [a for a in agents.values() if a]
    return {"robots": robots, "wall_s": round(wall, 1), "agents": agents,
            "max_cpu_s_per_stream_s": max((a["cpu_s_per_stream_s"] for a in ok), default=None),
            "max_peak_rss_mb": max((a["peak_rss_mb"] for a in ok), default=None),
            "team_ate_m": res.get("team", {}).get("ate_rmse_m")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", nargs="+", default=["office3", "office3-off"], choices=sorted(CASES))
    ap.add_argument("--scenario", default="sims/office.toml")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repo", type=Path, default=REPO, help="the checkout whose code runs (default: this one)")
    ap.add_argument("--stages", action="store_true", help="also a cProfile breakdown by stage (slower)")
    ap.add_argument("--json", action="store_true", help="print the JSON summary only")
    args = ap.parse_args()
    repo = args.repo.resolve()
    runs: dict[str, dict] = {}
    for name in args.cases:
        c = CASES[name]
        if c.get("launch"):
            runs[name] = run_launch(repo, args.scenario, args.seed, int(c["robots"]))  # type: ignore[call-overload]
        else:
            runs[name] = run_sim(repo, args.scenario, args.seed, int(c["robots"]), str(c["mode"]),  # type: ignore[call-overload]
                                 str(c["map_consensus"]), args.stages)
        if not args.json:
            print(name, json.dumps(runs[name]), flush=True)
    ref_name = args.cases[0]
    ref = runs[ref_name]
    targets: dict[str, dict[str, object]] = {}  # name -> value and at_least or at_most
    for name, r in runs.items():
        if "failed" in r:
            continue
        if "realtime_factor" in r and CASES[name]["map_consensus"] == "exact":
            targets[f"{name}_realtime_factor"] = {"value": r["realtime_factor"],
                                                  "at_least": 5.0 if r["robots"] <= 3 else 1.5}
        if name == "launch3":
            targets["launch3_cpu_s_per_stream_s"] = {"value": r["max_cpu_s_per_stream_s"], "at_most": 0.2}
            targets["launch3_peak_rss_mb"] = {"value": r["max_peak_rss_mb"], "at_most": 400}
    if all(n in runs and "failed" not in runs[n] for n in ("office3", "office8")):
        targets["office8_rss_per_robot_vs_office3"] = {
            "value": runs["office8"]["peak_rss_mb_per_robot"] / runs["office3"]["peak_rss_mb_per_robot"],
            "at_most": 1.5}
    for t in targets.values():
        v = t["value"]
        t["met"] = v is not None and (v >= t["at_least"] if "at_least" in t else v <= t["at_most"])  # type: ignore[operator]
    summary = {"repo": str(repo), "scenario": args.scenario, "seed": args.seed, "reference": ref_name,
               "runs": runs, "targets": targets,
               "vs_reference": {n: {"wall": r["wall_s"] / ref["wall_s"]} for n, r in runs.items()
                                if "failed" not in r and "failed" not in ref}}
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
