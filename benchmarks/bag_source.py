"""Keyframes per second through the bag path against the recorded-folder (npz) path, in one run.

The scenario's team is recorded once as a recorded folder (the reference) and as bags: ROS 2
PointCloud2, ROS 1 PointCloud2 and ROS 2 depth + semantic image + CameraInfo. Each source then
reads every keyframe of every robot: opening (the bag's metadata, and its index pass: motion,
scan headers, keyframe choice; a fixed cost per robot that dominates short bags) and
converting, best of ``--repeat``; ``keyframes_per_s_after_open`` is the rate past opening.
Reading must never be the bottleneck: the target is a bag path at least ``TARGET`` times faster
than one agent consumes keyframes (``Agent.process_keyframe`` on the first ``--agent-keyframes``
keyframes, measured here too).

    python benchmarks/bag_source.py --json [--scenario sims/small.toml] [--repeat 3]
"""

from __future__ import annotations

import argparse
import itertools
import json
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.io.bag.reader import BagSource
from kimera_multi_py.io.sources import RecordedSource
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.bag_recording import write_bag
from kimera_multi_py.sim.source import write_recording
from kimera_multi_py.team.build import params_for

TARGET = 10.0  # bag reading at least 10x the rate an agent consumes keyframes


def _best(f: Callable[[], Any], repeat: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t = time.perf_counter()
        out = f()
        best = min(best, time.perf_counter() - t)
    return best, out


def _read_all(make: Callable[[int], Any], robots: int) -> tuple[int, float]:
    """Keyframes read from every robot's source, and the seconds spent opening the sources."""
    t = time.perf_counter()
    sources = [make(r) for r in range(robots)]
    opened = time.perf_counter() - t
    return sum(sum(1 for _ in s) for s in sources), opened


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="sims/small.toml")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--agent-keyframes", type=int, default=30)
    ap.add_argument("--json", action="store_true", help="print JSON on one line")
    a = ap.parse_args()
    cfg = load_scenario(a.scenario)
    n_robots = len(cfg.robots)
    out: dict[str, Any] = {"scenario": a.scenario, "robots": n_robots, "target_ratio_vs_agent": TARGET}
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        write_recording(d / "npz", cfg, seed=a.seed)
        write_bag(d / "ros2_cloud", cfg, "ros2", seed=a.seed)
        write_bag(d / "ros1_cloud.bag", cfg, "ros1", seed=a.seed)
        write_bag(d / "ros2_camera", cfg, "ros2", seed=a.seed, camera=True)
        paths: dict[str, Callable[[int], Any]] = {
            "npz (reference)": lambda r: RecordedSource(d / "npz", r),
            "ros2_pointcloud2": lambda r: BagSource(d / "ros2_cloud", r),
            "ros1_pointcloud2": lambda r: BagSource(d / "ros1_cloud.bag", r),
            "ros2_depth_labels": lambda r: BagSource(d / "ros2_camera", r),
        }
        rates: dict[str, Any] = {}
        for name, make in paths.items():
            t, (n, opened) = _best(lambda m=make: _read_all(m, n_robots), a.repeat)
            rates[name] = {"keyframes": n, "seconds": t, "open_s": opened, "keyframes_per_s": n / t,
                           "keyframes_per_s_after_open": n / (t - opened)}
        out["sources"] = rates
        ref = rates["npz (reference)"]["keyframes_per_s"]
        for r in rates.values():
            r["ratio_vs_npz"] = r["keyframes_per_s"] / ref
        src = BagSource(d / "ros2_cloud", 0)
        agent = Agent(0, None, params_for(src))
        kfs = list(itertools.islice(src, a.agent_keyframes))
        t0 = time.perf_counter()
        for kf in kfs:
            agent.process_keyframe(kf)
        agent_rate = len(kfs) / (time.perf_counter() - t0)
        out["agent_keyframes_per_s"] = agent_rate
        slowest = min(r["keyframes_per_s"] for name, r in rates.items() if name != "npz (reference)")
        out["slowest_bag_ratio_vs_agent"] = slowest / agent_rate
        out["meets_target"] = slowest >= TARGET * agent_rate
    print(json.dumps(out, indent=None if a.json else 1))


if __name__ == "__main__":
    main()
