"""Robustness to perceptual aliasing: floor plans x seeds x team sizes x modes, against each robot's own knowledge.

    python benchmarks/team_robustness.py --json                    # 30 generated buildings + 2 files, {3,5,8} robots
    python benchmarks/team_robustness.py --quick                   # 2 generated buildings x 3 robots, distributed
    python benchmarks/team_robustness.py --scenarios gen:4 sims/office.toml --seeds 1 2 --robots 5 \
        --modes distributed centralized --jsonl runs.jsonl       # resumable: recorded runs are not run again
    python benchmarks/team_robustness.py --modes distributed centralized --report FILE.jsonl --codes OLD NEW
                                                                   # the table of recorded runs

Floor plans are scenario files and generated buildings: ``gen:B`` is building ``B`` of
:func:`building_args` (:func:`kimera_multi_py.sim.generate.generate_building`: its rooms, identical
rooms, halls, corridors and people drawn from ``B``, generated for the run's team size). Nobody
tunes to a generated building: the sweep's default draws 30 of them.

Every run is the single-process simulation (``SimRunner``) as a user runs it: default settings,
the exact team map on, scoring on (``--team-map off`` for the back end alone, recorded in the
run), each in a fresh process. Per run it reports the loop closures (inter- and intra-robot; true
and false; accepted and rejected by PCM and by the back end's GNC), each robot's frame-alignment
outcome against the ground truth (``true``: its estimate sits in the team frame; ``aliased``: in a
frame off by more than ``ALIASED_M``; ``excluded``: the robot kept itself out of the team frame,
scored as dead reckoning) and its own ``alignment`` report (reasons and the evidence per
hypothesis), whether it shares a non-repeated place with another robot (``shares_distinct``: the
generator knows; then aligning in the true frame is the expected outcome), team ATE, the robots'
registration odometry ATE and dead reckoning's (each anchored at its true start: references
measured in the same run), and wall time. A distributed run also reports the centralised solve of
its own joint graph (``same_graph_central_ate_m``). The summary checks the targets: 0 false
closures accepted, team ATE <= registration odometry and <= 0.5 x dead reckoning, distributed <=
1.05 x centralised, >= 80 % of the true inter-robot closures verified accepted, and the share of
robots sharing a distinct place that end in the true frame; it lists every robot kept out, with
its reason.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
FILES = [str(REPO / "sims" / "office.toml"), str(REPO / "sims" / "aliased_wing.toml")]
BUILDINGS = 30  # generated buildings in the default sweep
SCENARIOS = [f"gen:{b}" for b in range(BUILDINGS)] + FILES
ALIASED_M = 1.5  # a robot whose frame is off by more than this (at its own poses) is in an alias frame

_CHILD = r"""
import json, sys, tempfile
sys.path.insert(0, {repo!r})
sys.path.insert(0, {bench!r})
from team_robustness import measure
print(json.dumps(measure({scenario!r}, {robots}, {seed}, {mode!r}, {team_map!r})))
"""



def building_args(building: int, robots: int) -> dict[str, Any]:
    """The arguments of generated building ``building`` for a team of ``robots``, drawn from the
    building's number: every run of the sweep sees the same floor plan for it."""
    import numpy as np

    rng = np.random.default_rng([7919, building])
    halls, rooms, repeat, groups = int(rng.integers(0, 3)), int(rng.integers(6, 13)), int(rng.integers(2, 5)), \
        int(rng.integers(1, 3))
    return {"seed": building, "rooms": max(rooms, robots - halls, groups * repeat + 1), "repeat": repeat,
            "groups": groups, "halls": halls, "corridors": int(rng.integers(1, 3)),
            "people": int(rng.integers(0, 3)), "robots": robots, "visits": int(rng.integers(3, 6)),
            "name": f"gen{building}"}


def scenario_config(scenario: str, robots: int) -> Any:
    """The scenario of a sweep entry: a file, or ``gen:B`` (generated building ``B``)."""
    from kimera_multi_py.sim import load_scenario
    from kimera_multi_py.sim.generate import generate_building

    if scenario.startswith("gen:"):
        return generate_building(**building_args(int(scenario[4:]), robots))
    return load_scenario(scenario, robots=robots)


def scenario_name(scenario: str) -> str:
    return f"gen{scenario[4:]}" if scenario.startswith("gen:") else Path(scenario).stem


def shares_distinct(cfg: Any) -> list[bool]:
    """Per robot: does it visit a non-repeated place that another robot visits too (a place where
    only the true frame is consistent)?"""
    from kimera_multi_py.sim.generate import distinct_places

    places = distinct_places(cfg)
    return [any(places[r] & places[o] for o in places if o != r) for r in sorted(places)]


def same_graph_central_ate(agents: list[Any], truth: list[Any]) -> float:
    """Team ATE of the centralised robust solve (gtsam GNC, with the agents' closure votes) of
    the joint graph the distributed agents ended with: the back ends compared on the same
    evidence. The front end reads no estimate, so the centralised *mode* verifies the same closures
    too; it differs in its back end (no votes, the server's frame screen)."""
    import numpy as np

    from kimera_multi_py.agent.team_graph import joint_graph
    from kimera_multi_py.eval.team import trajectory_results
    from kimera_multi_py.pgo.centralised import solve_centralized

    graph, _ = joint_graph(agents)
    # the votes the agents' own solve used, in joint_graph's edge order: every robot's intra
    # edges, then each robot's inter edges towards higher ids (the verifier's copy)
    local = [a.local_graph() for a in agents]
    votes = np.concatenate([lg.intra_vote for lg in local]
                           + [lg.inter_vote[lg.inter_peer > lg.robot] for lg in local])
    graph.information = graph.information * votes[:, None, None]
    sol = solve_centralized(graph, robust=True, votes=votes)
    est = [sol.poses[graph.robot_indices(a.robot)] for a in agents]
    return float(trajectory_results(truth, est, anchored=False)[1]["ate_rmse_m"])


def measure(scenario: str, robots: int, seed: int, mode: str, team_map: str = "exact") -> dict[str, Any]:
    """One run, scored (called in a child process)."""
    import tempfile

    import numpy as np

    from kimera_multi_py.eval.metrics import align_se3, ate_rmse
    from kimera_multi_py.eval.team import excluded_robots, scored_closures, team_frame_estimates, trajectory_results
    from kimera_multi_py.workflow.simulate import SimRunner

    cfg = scenario_config(scenario, robots)
    with tempfile.TemporaryDirectory() as d:
        # as users run it: the exact team map on and scoring on, unless --team-map off asks for
        # the back end alone (no map, no map or scene-graph scores)
        off = {"map_consensus": "off", "quality": False} if team_map == "off" else {}
        runner = SimRunner(cfg, seed=seed, mode=mode, out_dir=d, **off)
        res = runner.run()
    truth = [np.array(tr.true) for tr in runner.tracks]
    odom = [np.array(tr.est) for tr in runner.tracks]
    reg = [np.array(a.scan_odometry.poses) if a.scan_odometry is not None else np.array(a.dead_reckoning)
           for a in runner.agents]
    outcomes = runner.outcomes
    est = [o.poses for o in outcomes]
    report = [dict(o.alignment) for o in outcomes]
    own = excluded_robots(outcomes)
    excluded = [r in own for r in range(len(est))]
    # excluded robots stay in their own frame: anchored at their true start, like dead reckoning
    scored = team_frame_estimates(truth, est, own)
    _, odo_team, _ = trajectory_results(truth, odom, anchored=True)
    _, reg_team, _ = trajectory_results(truth, reg, anchored=True)
    _, team, T_wt = trajectory_results(truth, est, anchored=False, own_frame=own)
    frames = []
    for r, (e, t) in enumerate(zip(scored, truth, strict=True)):
        if excluded[r]:
            frames.append("excluded")
            continue
        T_r = align_se3(e[:, :3, 3], t[:, :3, 3])
        p = np.c_[e[:, :3, 3], np.ones(len(e))]
        off = np.linalg.norm((p @ (T_r - T_wt).T)[:, :3], axis=1).mean()
        frames.append("aliased" if off > ALIASED_M else "true")
    scored_rows = scored_closures(truth, outcomes)
    closures: dict[str, int] = {}
    for kind, sel in (("inter", scored_rows[:, 0]), ("intra", ~scored_rows[:, 0])):
        pcm_ok, gnc_ok, true = scored_rows[sel, 1:].T
        for label, t in (("true", true), ("false", ~true)):
            closures[f"{kind}_{label}_verified"] = int(t.sum())
            closures[f"{kind}_{label}_rejected_pcm"] = int((t & ~pcm_ok).sum())
            closures[f"{kind}_{label}_rejected_gnc"] = int((t & pcm_ok & ~gnc_ok).sum())
            closures[f"{kind}_{label}_accepted"] = int((t & gnc_ok).sum())
    robot_ate = [ate_rmse(s[:, :3, 3], t[:, :3, 3]) for s, t in zip(scored, truth, strict=True)]
    ate, odo = float(team["ate_rmse_m"]), float(odo_team["ate_rmse_m"])
    same = {"same_graph_central_ate_m": same_graph_central_ate(runner.agents, truth)} if mode == "distributed" else {}
    return {**same, "scenario": scenario_name(scenario), "robots": robots, "seed": seed, "mode": mode,
            "team_map": team_map, "team_ate_m": ate, "odometry_ate_m": odo,
            "registration_ate_m": float(reg_team["ate_rmse_m"]), "ratio": ate / odo if odo > 0 else float("inf"),
            "shares_distinct": shares_distinct(cfg),
            "results_team_ate_m": float(res.team["ate_rmse_m"]), "robot_ate_m": robot_ate,
            "frames": frames, "alignment": report, "closures": closures, "wall_s": float(res.wall_s)}


def code_version() -> str:
    """The git trees of the package and the scenarios: runs measured on other code are not reused.
    ``+dirty`` when either has uncommitted changes; ``unknown`` outside a git checkout."""
    try:
        trees = subprocess.run(["git", "rev-parse", "HEAD:kimera_multi_py", "HEAD:sims"], cwd=REPO, check=True,
                               capture_output=True, text=True).stdout.split()
        dirty = subprocess.run(["git", "status", "--porcelain", "kimera_multi_py", "sims"], cwd=REPO, check=True,
                               capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return "-".join(t[:12] for t in trees) + ("+dirty" if dirty else "")


def run_one(scenario: str, robots: int, seed: int, mode: str, timeout: float, team_map: str = "exact"
            ) -> dict[str, Any]:
    code = _CHILD.format(repo=str(REPO), bench=str(REPO / "benchmarks"), scenario=scenario, robots=robots,
                         seed=seed, mode=mode, team_map=team_map)
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                             timeout=timeout)
    except subprocess.CalledProcessError as exc:
        return {"scenario": scenario_name(scenario), "robots": robots, "seed": seed, "mode": mode,
                "error": exc.stderr.strip().splitlines()[-1] if exc.stderr.strip() else "failed"}
    except subprocess.TimeoutExpired:
        return {"scenario": scenario_name(scenario), "robots": robots, "seed": seed, "mode": mode,
                "error": f"timeout after {timeout} s"}
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


def passes(run: dict[str, Any]) -> dict[str, bool]:
    """The issue's per-run targets."""
    if "error" in run:
        return {"ran": False}
    c = run["closures"]
    out = {"ran": True,
           "no_false_accepted": c["inter_false_accepted"] == 0 and c["intra_false_accepted"] == 0,
           "half_of_odometry": run["team_ate_m"] <= 0.5 * run["odometry_ate_m"],
           "not_above_odometry": run["team_ate_m"] <= run["odometry_ate_m"],
           "no_aliased_frame": "aliased" not in run["frames"],
           "true_inter_80pct": c["inter_true_accepted"] >= 0.8 * c["inter_true_verified"]}
    if "registration_ate_m" in run:
        out["not_above_registration"] = run["team_ate_m"] <= run["registration_ate_m"]
    return out


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts of runs meeting each target, distributed against centralised where both ran."""
    checks = [passes(r) for r in runs]
    keys = sorted({k for c in checks for k in c})
    out: dict[str, Any] = {"runs": len(runs), **{k: sum(bool(c.get(k)) for c in checks) for k in keys}}
    central = {(r["scenario"], r["robots"], r["seed"]): r for r in runs
               if r.get("mode") == "centralized" and "error" not in r}
    dist = [r for r in runs if r.get("mode") == "distributed" and "error" not in r]
    pairs = [(r, central[(r["scenario"], r["robots"], r["seed"])]) for r in dist
             if (r["scenario"], r["robots"], r["seed"]) in central]
    if pairs:
        out["distributed_vs_centralized"] = [
            {"scenario": d["scenario"], "robots": d["robots"], "seed": d["seed"],
             "ratio": d["team_ate_m"] / max(c["team_ate_m"], 1e-9),
             "ok": d["team_ate_m"] <= 1.05 * c["team_ate_m"]} for d, c in pairs]
        out["within_1.05_of_centralized"] = sum(p["ok"] for p in out["distributed_vs_centralized"])
    # the back ends on the same evidence (see same_graph_central_ate), where every robot ended in a
    # settled frame: a robot that did not (aligned on one place or on the consensus of a tie)
    # follows the settled ones without pulling them, which the joint solve does not do
    same = [r for r in dist if "same_graph_central_ate_m" in r and _all_settled(r)]
    if same:
        out["settled_runs"] = len(same)
        out["same_graph_ratio_max"] = max(r["team_ate_m"] / max(r["same_graph_central_ate_m"], 1e-9) for r in same)
        out["within_1.05_of_same_graph_central"] = sum(r["team_ate_m"] <= 1.05 * r["same_graph_central_ate_m"]
                                                       for r in same)
    # robots that share a non-repeated place with the team should end in the true frame; a
    # robot kept out is safe but not a success: every one is listed with its reason
    eligible = [(r, i) for r in runs if "error" not in r and "shares_distinct" in r
                for i, ok in enumerate(r["shares_distinct"]) if ok]
    if eligible:
        out["robots_sharing_a_distinct_place"] = len(eligible)
        out["of_them_in_the_true_frame"] = sum(r["frames"][i] == "true" for r, i in eligible)
    out["kept_out"] = [{"scenario": r["scenario"], "robots": r["robots"], "seed": r["seed"], "mode": r["mode"],
                        "robot": i, "shares_distinct": bool(r.get("shares_distinct", [False] * (i + 1))[i]),
                        "reason": (r["alignment"][i] if i < len(r["alignment"]) else {}).get("reason", "")}
                       for r in runs if "error" not in r for i, f in enumerate(r["frames"]) if f == "excluded"]
    out["false_accepted_total"] = sum(r["closures"]["inter_false_accepted"] + r["closures"]["intra_false_accepted"]
                                      for r in runs if "error" not in r)
    return out


def _all_settled(run: dict[str, Any]) -> bool:
    return all(a.get("settled", True) for a in run.get("alignment", []) if a.get("status") != "excluded")


def table(runs: list[dict[str, Any]]) -> str:
    head = (f"{'scenario':<13}{'mode':<12}{'n':>3}{'seed':>5}{'team':>8}{'reg':>8}{'odom':>8}{'ratio':>7}"
            f"{'inter T/F acc':>15}{'intra T/F acc':>15}{'frames':>20}{'wall s':>8}{'same-graph central':>20}")
    lines = [head, "-" * len(head)]
    for r in runs:
        if "error" in r:
            lines.append(f"{r['scenario']:<13}{r['mode']:<12}{r['robots']:>3}{r['seed']:>5}  error: {r['error']}")
            continue
        c = r["closures"]
        fr = "".join({"true": ".", "aliased": "A", "excluded": "x"}[f] for f in r["frames"])
        lines.append(f"{r['scenario']:<13}{r['mode']:<12}{r['robots']:>3}{r['seed']:>5}{r['team_ate_m']:>8.3f}"
                     f"{r.get('registration_ate_m', float('nan')):>8.3f}{r['odometry_ate_m']:>8.3f}{r['ratio']:>7.2f}"
                     f"{c['inter_true_accepted']:>9}/{c['inter_false_accepted']:<5}"
                     f"{c['intra_true_accepted']:>9}/{c['intra_false_accepted']:<5}{fr:>20}{r['wall_s']:>8.0f}"
                     + (f"{r['same_graph_central_ate_m']:>20.4f}" if "same_graph_central_ate_m" in r else ""))
    return "\n".join(lines)


def report(runs: list[dict[str, Any]], summary_: dict[str, Any]) -> str:
    """The table, then the summary with only the distributed/centralised pairs that miss 1.05x."""
    pairs = summary_.get("distributed_vs_centralized", [])
    brief = {**summary_, "distributed_vs_centralized": [p for p in pairs if not p["ok"]]} if pairs else summary_
    return table(runs) + "\n" + json.dumps(brief, indent=1)


RunKey = tuple[str, int, int, str]  # (scenario, robots, seed, mode)


def _records(path: Path) -> list[tuple[RunKey, dict[str, Any]]]:
    """The runs a ``--jsonl`` file holds, in order, with their keys; an unreadable file or a line
    that is not a run record stops the benchmark with one line naming it."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise SystemExit(f"{path}: cannot read it ({exc})") from None
    out = []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            r = json.loads(line)
            out.append(((r["scenario"], r["robots"], r["seed"], r["mode"]), r))
        except (ValueError, KeyError, TypeError) as exc:
            raise SystemExit(f"{path}, line {n}: not a run record ({exc!r})") from None
    return out


def _done_runs(path: Path, code: str) -> dict[RunKey, dict[str, Any]]:
    """Runs already recorded in a ``--jsonl`` file on this ``code``, by key."""
    if not path.exists() or code.endswith(("+dirty", "unknown")):
        return {}
    return {key: r for key, r in _records(path) if r.get("code") == code and "error" not in r}


def recorded_runs(path: Path, codes: list[str]) -> list[dict[str, Any]]:
    """The runs a ``--jsonl`` file holds on the code labels ``codes`` (prefixes of ``code``), one
    per (scenario, robots, seed, mode): a later label's run replaces an earlier one's."""
    chosen: dict[RunKey, tuple[int, dict[str, Any]]] = {}
    for key, r in _records(path):
        rank = [i for i, c in enumerate(codes) if str(r.get("code", "")).startswith(c)]
        if rank and (key not in chosen or rank[-1] >= chosen[key][0]):
            chosen[key] = (rank[-1], r)
    return [chosen[k][1] for k in sorted(chosen)]


def code_counts(runs: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Per mode, how many runs each code gave (a report names the code it stands on)."""
    out: dict[str, dict[str, int]] = {}
    for r in runs:
        per = out.setdefault(r["mode"], {})
        per[r.get("code", "unknown")] = per.get(r.get("code", "unknown"), 0) + 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=SCENARIOS)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="simulation seeds of a generated building")
    ap.add_argument("--robots", type=int, nargs="+", default=[3, 5, 8])
    ap.add_argument("--modes", nargs="+", default=["distributed"], choices=["distributed", "centralized"])
    ap.add_argument("--seeds-files", type=int, nargs="+", default=list(range(10)),
                    help="seeds of the scenario files (a generated building runs --seeds)")
    ap.add_argument("--team-map", choices=["exact", "off"], default="exact",
                    help="off: the back end alone, no team map and no map scores (recorded in each run)")
    ap.add_argument("--quick", action="store_true", help="2 generated buildings x 3 robots, distributed (the test)")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds per run")
    ap.add_argument("--json", action="store_true", help="print the JSON only")
    ap.add_argument("--jsonl", type=Path, help="append each run to this file as it ends; runs already in it, "
                    "measured on the same committed code, are not run again (a long sweep survives being "
                    "stopped; failed runs are recorded and run again)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="runs at once (default: one per core)")
    ap.add_argument("--report", type=Path, help="run nothing: the table and summary of the runs this --jsonl file "
                    "holds (of the chosen scenarios, robots, seeds and modes) on the --codes labels")
    ap.add_argument("--codes", nargs="+", help="with --report: code labels (prefixes of a run's code), oldest first; "
                    "a later label's run replaces an earlier one's (default: the current code)")
    args = ap.parse_args()
    if args.quick:
        args.scenarios, args.seeds, args.robots = ["gen:0", "gen:1"], [0], [3]
    code = code_version()
    if args.report:
        stems = {scenario_name(s) for s in args.scenarios}
        seeds = set(args.seeds) | set(args.seeds_files)
        runs = [r for r in recorded_runs(args.report, args.codes or [code]) if r["scenario"] in stems
                and r["robots"] in args.robots and r["seed"] in seeds and r["mode"] in args.modes]
        codes, sums = code_counts(runs), summary(runs)
        print(json.dumps({"codes": codes, "runs": runs, "summary": sums}, indent=1) if args.json
              else report(runs, {"codes": codes, **sums}))
        return
    jobs = [(s, n, seed, m) for s in args.scenarios for n in args.robots
            for seed in (args.seeds if s.startswith("gen:") else args.seeds_files) for m in args.modes]
    done = _done_runs(args.jsonl, code) if args.jsonl else {}

    def one(job: tuple[str, int, int, str]) -> dict[str, Any]:
        key = (scenario_name(job[0]), job[1], job[2], job[3])
        if key in done and done[key].get("team_map", "off") == args.team_map:
            return done[key]
        run = {**run_one(*job, args.timeout, team_map=args.team_map), "code": code}
        if args.jsonl:  # failed runs too (the report lists them); a resumed sweep runs them again
            with lock, args.jsonl.open("a") as f:
                f.write(json.dumps(run) + "\n")
        return run

    lock = threading.Lock()
    # each run is its own process: run as many at once as there are cores (--jobs)
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        runs = list(pool.map(one, jobs))
    sums = summary(runs)
    print(json.dumps({"code": code, "runs": runs, "summary": sums}, indent=1) if args.json else report(runs, sums))


if __name__ == "__main__":
    main()
