"""Bytes on the wire: one scenario run with the compact encodings and with the full-size ones.

    python benchmarks/bandwidth.py --json                       # office, 3 robots, seed 0, both formats
    python benchmarks/bandwidth.py --formats compact --robots 5 --scenario sims/aliased_wing.toml
    python benchmarks/bandwidth.py --json --suite               # office 3 and 8, aliased_wing 5 (hours)

Each format runs in a fresh process (``node.compact_wire`` true or false; docs/architecture.md,
"Bytes on the wire"): the full-size run is the reference measured in the same invocation. Per run
it reports bytes per topic, the total, MB per km of team travel (the true paths' length), the
team ATE, the true and false inter-robot closures, the map agreement with the centralised fusion
and the team map's F1 / mIoU, kB per robot per simulated second (flat or falling with the team
size is the aim), and each robot's share of the map evidence against the size of the final
lossless team map (``robot0/team_map.kmo``); then each compact figure beside the full-size one.
``--suite`` runs the three cases of docs/benchmarks.md ("Larger teams") one after the other.
Also ``--from-results DIR/results.json``: the same figures of a run made with ``kimera-multi sim``
(the team map's size read from ``DIR/robot0/team_map.kmo`` when it is there).

The link-budget sweep (docs/deployment.md, "Link budget") runs the compact format once per budget:

    python benchmarks/bandwidth.py --json --scenario sims/tiny.toml --robots 2 --budgets unlimited 200 50 20

and reports per budget the same figures plus each link's queue delay, what could not be sent
(dropped, still queued at the end) and the seconds from the streams' end until every robot's
team map was whole (``team_maps_complete_s``; null: not within the run).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FORMATS = {"compact": True, "full": False}

_CHILD = r"""
import json, sys, tempfile
from pathlib import Path
sys.path.insert(0, {repo!r})
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.team.config import KimeraConfig
from kimera_multi_py.workflow.simulate import SimRunner
cfg = load_scenario({scenario!r}, robots={robots})
config = KimeraConfig.defaults().updated({{"node": {{"compact_wire": {compact!r}, "link_budget": {budget!r},
                                                    "link_policy": {policy!r}}}}})
with tempfile.TemporaryDirectory() as d:
    res = SimRunner(cfg, seed={seed}, mode="distributed", out_dir=d, config=config).run().to_dict()
    kmo = Path(d) / "robot0" / "team_map.kmo"
    res["team_map_file_bytes"] = kmo.stat().st_size if kmo.exists() else None
print(json.dumps(res, default=str))
"""
SUITE = (("office.toml", 3), ("office.toml", 8), ("aliased_wing.toml", 5))


def summarise(res: dict) -> dict:
    """The figures of one run from its ``results.json`` dict (and ``team_map_file_bytes``, the size
    of robot 0's final team map file, when the caller read it)."""
    sent = res["bytes_sent"]
    travel_km = res["team"]["trajectory_length_m"] / 1e3
    robots, seconds = len(res["robots"]), res.get("sim_seconds")
    kmo = res.get("team_map_file_bytes")
    evidence = sent["per_topic"].get("map/evidence", 0)
    agreement = [a["identical"] for a in res.get("map_consensus", {}).get("agreement", {}).values()]
    lc = res["loop_closures"]
    return {
        "robots": robots, "travel_m": res["team"]["trajectory_length_m"],
        "bytes_total": sent["total"], "bytes_by_topic": dict(sent["per_topic"]),
        "mb_per_km": sent["total"] / 1e6 / travel_km if travel_km else None,
        "kb_per_robot_per_s": sent["total"] / 1e3 / robots / seconds if seconds else None,
        "team_map_file_bytes": kmo,
        "evidence_per_robot_vs_team_map": evidence / robots / kmo if kmo else None,
        "team_ate_m": res["team"]["ate_rmse_m"],
        "true_accepted_inter": lc["true_accepted_inter"], "false_accepted_inter": lc["false_accepted_inter"],
        "map_agreement_min": min(agreement) if agreement else None,
        "team_map_f1": res.get("team_map", {}).get("occupancy_f1"),
        "team_map_miou": res.get("team_map", {}).get("semantic_miou"),
        "refused_messages": res.get("refused_messages"),
        "sim_seconds": res.get("sim_seconds"),
        "wall_s": res["wall_s"],
        **_link_figures(res.get("link_budget") or {}),
    }


def _link_figures(lb: dict) -> dict:
    """The link budget's figures of a run (none without a budget but the maps' completion)."""
    links = lb.get("links") or {}
    out: dict = {"link_budget_kbps": lb.get("kbps"), "team_maps_complete_s": lb.get("team_maps_complete_s")}
    if links:
        n = sum(v["messages"] for v in links.values())
        out.update(
            queue_delay_mean_s=sum(v["queue_delay_mean_s"] * v["messages"] for v in links.values()) / n if n else 0.0,
            queue_delay_max_s=max(v["queue_delay_max_s"] for v in links.values()),
            control_delay_max_s=max(v["queue_delay_max_s_by_class"]["control"] for v in links.values()),
            dropped_messages=sum(v["dropped_messages"] for v in links.values()),
            queued_messages_at_end=sum(v["queued_messages"] for v in links.values()),
            link_bytes={k: v["bytes"] for k, v in links.items()})
    return out


def run_one(scenario: str, robots: int, seed: int, compact: bool, budget: float | None = None,
            policy: str = "priority") -> dict:
    code = _CHILD.format(repo=str(REPO), scenario=scenario, robots=robots, seed=seed, compact=compact,
                         budget=budget, policy=policy)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return summarise(json.loads(out.stdout.strip().splitlines()[-1]))


def compare(runs: dict[str, dict]) -> dict[str, object]:
    """Each compact figure beside the full-size one (bytes per topic, total, MB/km, ATE, closures, map)."""
    c, f = runs["compact"], runs["full"]
    topics = sorted(set(c["bytes_by_topic"]) | set(f["bytes_by_topic"]))
    both = ("mb_per_km", "team_ate_m", "true_accepted_inter", "false_accepted_inter", "map_agreement_min",
            "team_map_f1", "team_map_miou")
    return {
        "bytes_by_topic": {t: {"compact": c["bytes_by_topic"].get(t, 0), "full": f["bytes_by_topic"].get(t, 0)}
                           for t in topics},
        "bytes_total_ratio": c["bytes_total"] / f["bytes_total"],
        **{k: {"compact": c[k], "full": f[k]} for k in both},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default=str(REPO / "sims" / "office.toml"))
    ap.add_argument("--robots", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--formats", nargs="+", choices=sorted(FORMATS), default=["compact", "full"])
    ap.add_argument("--from-results", nargs="+", default=[], metavar="FORMAT=RESULTS_JSON",
                    help="summarise existing runs (e.g. compact=/tmp/run/results.json) instead of running")
    ap.add_argument("--budgets", nargs="+", default=[], metavar="KBPS",
                    help="link-budget sweep (compact format): 'unlimited' or kB/s per link, e.g. unlimited 200 50 20")
    ap.add_argument("--policy", choices=["priority", "fifo"], default="priority", help="the sweep's link scheduling")
    ap.add_argument("--suite", action="store_true",
                    help="office with 3 and 8 robots and aliased_wing with 5, each in --formats")
    ap.add_argument("--json", action="store_true", help="print the JSON summary only")
    args = ap.parse_args()
    if args.budgets:
        sweep(args)
        return
    if args.suite:
        suite(args)
        return
    runs = {}
    for item in args.from_results:
        name, _, path = item.partition("=")
        res = json.loads(Path(path).read_text())
        kmo = Path(path).parent / "robot0" / "team_map.kmo"
        res.setdefault("team_map_file_bytes", kmo.stat().st_size if kmo.exists() else None)
        runs[name] = summarise(res)
    for name in [] if runs else args.formats:
        runs[name] = run_one(args.scenario, args.robots, args.seed, FORMATS[name])
        print(json.dumps({name: runs[name]}), file=sys.stderr, flush=True)  # progress: one run per line
    summary: dict[str, object] = {"scenario": Path(args.scenario).name, "robots": args.robots, "seed": args.seed,
                                  "runs": runs}
    if set(runs) == set(FORMATS):
        summary["compact_vs_full"] = compare(runs)
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    print(f"{'format':>8} {'MB':>7} {'MB/km':>7} {'ATE [m]':>8} {'true':>5} {'false':>5}")
    for name, r in runs.items():
        print(f"{name:>8} {r['bytes_total'] / 1e6:>7.2f} {r['mb_per_km']:>7.1f} {r['team_ate_m']:>8.3f} "
              f"{r['true_accepted_inter']:>5} {r['false_accepted_inter']:>5}")
    topics = sorted({t for r in runs.values() for t in r["bytes_by_topic"]})
    print(f"{'topic':>22} " + " ".join(f"{n:>10}" for n in runs))
    for t in topics:
        print(f"{t:>22} " + " ".join(f"{r['bytes_by_topic'].get(t, 0) / 1e6:>9.3f}M" for r in runs.values()))


def suite(args: argparse.Namespace) -> None:
    """The three cases of docs/benchmarks.md ("Larger teams"), each in every format of ``--formats``; the compact
    kB per robot per second side by side, to see whether it stays flat as the team grows."""
    cases: dict[str, dict[str, object]] = {}
    per_second: dict[str, float] = {}
    for name, robots in SUITE:
        runs = {}
        for fmt in args.formats:
            runs[fmt] = run_one(str(REPO / "sims" / name), robots, args.seed, FORMATS[fmt])
            print(json.dumps({f"{name}:{robots}:{fmt}": runs[fmt]}), file=sys.stderr, flush=True)
        case: dict[str, object] = {"scenario": name, "robots": robots, "runs": runs}
        if set(runs) == set(FORMATS):
            case["compact_vs_full"] = compare(runs)
        cases[f"{name}:{robots}"] = case
        if "compact" in runs:
            per_second[f"{name}:{robots}"] = runs["compact"]["kb_per_robot_per_s"]
    summary = {"seed": args.seed, "cases": cases, "compact_kb_per_robot_per_s": per_second}
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    for key, rate in per_second.items():
        print(f"{key:>24} {rate:>8.2f} kB per robot per s")


def budget_value(label: str) -> float | None:
    """``unlimited`` -> None, else kB/s."""
    if label == "unlimited":
        return None
    value = float(label)
    if not value > 0:
        raise SystemExit(f"--budgets: {label!r} is not 'unlimited' or kB/s > 0")
    return value


def sweep(args: argparse.Namespace) -> None:
    """One compact run per link budget (each in a fresh process), the figures side by side."""
    budgets = [(label, budget_value(label)) for label in args.budgets]
    runs = {}
    for label, kbps in budgets:
        runs[label] = run_one(args.scenario, args.robots, args.seed, True, kbps, args.policy)
        print(json.dumps({label: runs[label]}), file=sys.stderr, flush=True)
    summary = {"scenario": Path(args.scenario).name, "robots": args.robots, "seed": args.seed,
               "policy": args.policy, "budget_sweep": runs}
    if args.json:
        print(json.dumps(summary, indent=1))
        return
    print(f"{'kB/s':>9} {'MB':>7} {'ATE [m]':>8} {'true':>5} {'false':>5} {'delay max':>9} {'dropped':>7} "
          f"{'complete [s]':>12}")
    for label, r in runs.items():
        done = r.get("team_maps_complete_s")
        print(f"{label:>9} {r['bytes_total'] / 1e6:>7.2f} {r['team_ate_m']:>8.3f} {r['true_accepted_inter']:>5} "
              f"{r['false_accepted_inter']:>5} {r.get('queue_delay_max_s', 0.0):>9.1f} "
              f"{r.get('dropped_messages', 0):>7} {'-' if done is None else f'{done:.1f}':>12}")


if __name__ == "__main__":
    main()
