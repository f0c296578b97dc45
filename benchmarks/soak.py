"""Soak: a team of agent processes under a seeded schedule of faults over a long stream, then a
check that nothing was lost.

    python benchmarks/soak.py --json                      # 4 robots, 20 min of stream, --rate 2
    python benchmarks/soak.py --json --short              # 2 min, one fault of each kind

The scenario loops: ``sims/faults.toml``'s building with every robot's two-room route repeated
until the stream is ``--minutes`` long. The schedule (``--seed``) draws SIGKILL + ``--resume`` of
agents, router restarts and link partitions over the stream (``launch``'s faults; message loss is
not among them: the processes talk over TCP, whose links lose no message, and the loss cases
run in ``kimera-multi sim``, ``benchmarks/faults.py``). While the team runs, a sampler reads
every agent's checkpoint (each must load) and every process's resident memory. At the end:

* every keyframe in every trajectory, once and in order (against the simulator's plan);
* every closure a killed robot held at its last checkpoint, in its final closure list;
* each team map against the centralised fusion of every robot's final evidence
  (``identical``), and the robots' team maps against each other;
* checkpoints read during the run and after it, and how many failed to load (must be 0);
* per process, the slope of resident memory after warm-up (MB per minute of wall time).

Prints one JSON object (``--json``) with the schedule and the figures (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import json
import random
import re
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from kimera_multi_py.agent.checkpoint import load_checkpoint  # noqa: E402
from kimera_multi_py.comms.loopback import Partition  # noqa: E402
from kimera_multi_py.core.errors import CheckpointError  # noqa: E402
from kimera_multi_py.eval.map_metrics import agreement  # noqa: E402
from kimera_multi_py.io.tum import read_tum  # noqa: E402
from kimera_multi_py.mapping.octree_io import load_octree  # noqa: E402
from kimera_multi_py.mapshare.fusion import centralised_team_map, octree_cells  # noqa: E402
from kimera_multi_py.sim import Simulation, load_scenario  # noqa: E402
from kimera_multi_py.team.config import KimeraConfig  # noqa: E402
from kimera_multi_py.team.launcher import Kill, launch, launch_job  # noqa: E402

BASE = ROOT / "sims" / "faults.toml"
ROUTES = (["office", "meeting"], ["meeting", "lounge"], ["lounge", "office"], ["office", "lounge"])
REP_STREAM_S = 45.0  # stream s per repetition of the two-room routes, roughly (2 reps: 94 s; 4 reps: 204 s)
PGO_PERIOD = 20.0
SAMPLE_S = 5.0


def looping_scenario(path: Path, minutes: float, robots: int) -> Path:
    """``faults.toml`` with ``robots`` robots whose routes repeat until ``minutes`` of stream."""
    text = BASE.read_text()
    head, tail = text.split("[[robots]]", 1)[0], "[sensor]" + text.split("[sensor]", 1)[1]
    reps = max(1, round(minutes * 60.0 / REP_STREAM_S))
    blocks = []
    for r in range(robots):
        route = ROUTES[r % len(ROUTES)] * reps
        blocks.append(f'[[robots]]\nroute = {json.dumps(route)}\nspeed = 1.0\nturn_rate_deg = 90.0\n')
    path.write_text(head.replace('name = "faults"', 'name = "soak"') + "\n".join(blocks) + "\n" + tail)
    return path


def schedule(rng: random.Random, ends: list[float], short: bool) -> dict[str, Any]:
    """Seeded faults over the stream: kills (at the killed robot's own stream time, inside its
    stream, whose end is ``ends[robot]``), router restarts and partitions (team stream time)."""
    robots, duration = len(ends), max(ends)
    n = 1 if short else max(2, int(duration // 240))
    lo, hi = 0.15 * duration, 0.8 * duration
    kills = []
    for _ in range(n):
        r = rng.randrange(robots)
        kills.append((r, round(rng.uniform(0.15 * ends[r], 0.8 * ends[r]), 1)))
    kills.sort()
    restarts = sorted(round(rng.uniform(lo, hi), 1) for _ in range(n))
    parts = []
    for _ in range(n):
        start = round(rng.uniform(lo, hi), 1)
        cut = rng.randrange(1, robots)
        parts.append((cut, start, round(start + rng.uniform(10.0, 30.0), 1)))
    return {"kills": kills, "router_restarts": restarts, "partitions": sorted(parts, key=lambda p: p[1])}


class Sampler(threading.Thread):
    """Every ``SAMPLE_S``: each process's resident memory, and each agent's checkpoint loaded."""

    def __init__(self, out: Path, robots: int) -> None:
        super().__init__(daemon=True)
        self.out, self.robots = out, robots
        self.stop = threading.Event()
        self.memory: dict[str, list[tuple[float, float]]] = {}
        self.checkpoints_read = 0
        self.checkpoint_failures: list[str] = []

    def run(self) -> None:
        import psutil

        t0 = time.monotonic()
        me = psutil.Process()
        while not self.stop.wait(SAMPLE_S):
            now = (time.monotonic() - t0) / 60.0
            for p in me.children(recursive=True):
                try:
                    cmd = " ".join(p.cmdline())
                    rss = p.memory_info().rss / 1e6
                except psutil.Error:
                    continue
                m = re.search(r"agent --robot (\d+)", cmd)
                name = f"robot{m.group(1)}" if m else "router" if " router " in cmd else None
                if name is not None:
                    self.memory.setdefault(name, []).append((now, rss))
            for r in range(self.robots):
                self.read(self.out / f"robot{r}" / "checkpoint.kmc")

    def read(self, path: Path) -> None:
        if not path.exists():
            return
        try:
            load_checkpoint(path)
            self.checkpoints_read += 1
        except CheckpointError as exc:
            self.checkpoint_failures.append(str(exc))


def memory_slopes(samples: dict[str, list[tuple[float, float]]]) -> dict[str, dict[str, float]]:
    """Per process: MB per minute of a line fitted after warm-up (the first quarter of its
    samples; a restarted process's samples restart the fit), and the last resident size."""
    out = {}
    for name, pts in sorted(samples.items()):
        arr = np.array(pts)
        if len(arr) < 8:
            continue
        tail = arr[len(arr) // 4:]
        slope = float(np.polyfit(tail[:, 0], tail[:, 1], 1)[0]) if np.ptp(tail[:, 0]) > 0 else 0.0
        out[name] = {"mb_per_min": round(slope, 3), "last_mb": round(float(arr[-1, 1]), 1), "samples": len(arr)}
    return out


def closures_kept(out: Path, robots: int, kills: list[dict[str, Any]]) -> dict[str, Any]:
    """Inter-robot closures accepted (each is held by one robot of the pair), and any closure a
    killed robot held at its last checkpoint before the kill that its final list lacks."""
    final = {}
    for r in range(robots):
        data = json.loads((out / f"robot{r}" / "closures.json").read_text())
        final[r] = {(c["own_kf"], c["peer"], c["peer_kf"]): c["accepted"] for c in data["closures"]}
    accepted = sum(ok for r in final for k, ok in final[r].items() if k[1] != r)
    lost = []
    for k in kills:
        if k.get("checkpoint"):
            before = load_checkpoint(k["checkpoint"])[0]
            kept = {(c.own_kf, peer, c.peer_kf) for peer, group in before.closures.items() for c in group}
            lost += [[k["robot"], *x] for x in sorted(kept - set(final[k["robot"]]))]
    return {"accepted_inter": int(accepted), "lost_at_kills": lost}


def team_maps(out: Path, robots: int) -> dict[str, Any]:
    """Each robot's team map against the centralised fusion of every robot's final evidence."""
    maps = {r: load_checkpoint(out / f"robot{r}" / "checkpoint.kmc")[0].map for r in range(robots)}
    ref = octree_cells(centralised_team_map(maps))
    fig = {}
    for r in range(robots):
        path = out / f"robot{r}" / "team_map.kmo"
        if path.exists():
            fig[str(r)] = agreement(octree_cells(load_octree(path)), ref)["identical"]
    return {"identical_to_centralised_fusion": fig, "cells": int(len(ref[0]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--short", action="store_true", help="2 minutes of stream, one fault of each kind")
    ap.add_argument("--minutes", type=float, default=None, help="stream length (default 20, --short 2)")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--rate", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=None, help="run folder (default: a temporary one)")
    args = ap.parse_args()
    minutes = args.minutes if args.minutes is not None else 2.0 if args.short else 20.0
    out = args.out or Path(tempfile.mkdtemp(prefix="soak-"))
    out.mkdir(parents=True, exist_ok=True)
    scenario = looping_scenario(out / "soak.toml", minutes, args.robots)
    sim = Simulation(load_scenario(scenario), args.seed)
    plan = schedule(random.Random(args.seed), [float(p.stamps[-1]) for p in sim.plans], args.short)
    config = KimeraConfig.defaults().updated({
        "run": {"scenario": str(scenario), "robots": args.robots, "seed": args.seed, "mode": "distributed"},
        "schedule": {"period": PGO_PERIOD}})
    job = launch_job(config, out / "run", rate=args.rate, checkpoint_every=5.0,
                     timeout=max(3600.0, 6 * sim.duration / args.rate),
                     kills=[Kill(r, at) for r, at in plan["kills"]], router_restarts=plan["router_restarts"])
    job.partitions = [Partition((frozenset(set(range(args.robots)) - {c}), frozenset({c})), s, e)
                      for c, s, e in plan["partitions"]]
    sampler = Sampler(job.out_dir, args.robots)
    sampler.start()
    t0 = time.perf_counter()
    results = launch(job).to_dict()
    wall = time.perf_counter() - t0
    sampler.stop.set()
    sampler.join()
    run = job.out_dir
    for f in sorted((run / "logs").glob("*.killed.kmc")) + sorted(run.glob("robot*/checkpoint.kmc")):
        sampler.read(f)
    trajectories = {}
    for r, p in enumerate(sim.plans):
        stamps, _ = read_tum(run / f"robot{r}" / "trajectory.tum")
        trajectories[str(r)] = {"keyframes": len(stamps), "planned": len(p.stamps),
                                "once_in_order": bool(len(stamps) == len(p.stamps)
                                                      and np.allclose(stamps, p.stamps, atol=1e-6, rtol=0))}
    faults = json.loads((run / "faults.json").read_text())
    fig = {
        "robots": args.robots, "stream_s": round(sim.duration, 1), "rate": args.rate, "seed": args.seed,
        "wall_s": round(wall, 1), "schedule": plan, "faults_done": faults,
        "trajectories": trajectories, "closures": closures_kept(run, args.robots, faults["kills"]),
        "team_maps": {**team_maps(run, args.robots), "agree": results.get("map_consensus", {}).get("agree")},
        "linger": results.get("linger"),
        "checkpoints": {"read": sampler.checkpoints_read, "unreadable": sampler.checkpoint_failures},
        "memory": memory_slopes(sampler.memory), "team_ate_m": results["team"]["ate_rmse_m"],
        "out": str(run),
    }
    fig["nothing_lost"] = bool(all(t["once_in_order"] for t in trajectories.values())
                               and not fig["closures"]["lost_at_kills"] and not sampler.checkpoint_failures)
    if args.json:
        print(json.dumps(fig), flush=True)
    else:
        print(json.dumps(fig, indent=1))


if __name__ == "__main__":
    main()
