"""ZenohBus between two processes against raw zenoh-python, same payloads, same sessions, same run.

For 1 KB and 100 KB payloads it measures:

- latency: sequential round trips (ping -> echo -> back), p50/p99 in microseconds;
- throughput: N messages published back to back (congestion control BLOCK, so nothing is
  dropped) until the receiver reports its count; messages/s end to end.

The raw baseline is zenoh-python as its own examples use it (``z_ping``/``z_pong``,
``z_pub_thr``/``z_sub_thr``): bytes put on a declared publisher, the echo and the count done in
the subscriber callback. The ZenohBus path does everything the system does: encode a ``Ping``
message into the envelope, hand each sample to asyncio, decode and validate, and (for echoes)
re-encode. Both run over the same pair of sessions (the bus's own), one after the other.

Overheads reported: ``throughput_ratio`` = bus / raw (target >= 0.5) and
``p50_latency_ratio`` = bus / raw (target <= 2).

    python benchmarks/comms.py --json
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.messages import Heartbeat, Ping
from kimera_multi_py.comms.zenoh_bus import ZenohBus

REPO = Path(__file__).resolve().parents[1]
TEAM = "bench"
RAW_LAT, RAW_LAT_ECHO = "bench_raw/lat", "bench_raw/lat_echo"
RAW_THR, RAW_THR_DONE = "bench_raw/thr", "bench_raw/thr_done"
BULK = "diag/bulk"
SIZES = {"1KB": 1024, "100KB": 100 * 1024}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def percentiles(ns: list[int]) -> dict[str, float]:
    us = np.asarray(ns, dtype=np.float64) / 1e3
    return {"p50_us": float(np.percentile(us, 50)), "p99_us": float(np.percentile(us, 99)),
            "mean_us": float(us.mean()), "samples": len(ns)}


# ---------------------------------------------------------------------------- child (echo side)
async def child(connect: str, queue_size: int) -> None:
    bus = ZenohBus(TEAM, 1, connect=[connect], block_on_congestion=True, queue_size=queue_size)
    async with bus:
        session = bus.session
        # raw: echo and count in the callbacks, as zenoh-python's examples do
        echo_pub = session.declare_publisher(RAW_LAT_ECHO,
                                             congestion_control=zenoh.CongestionControl.BLOCK)
        done_pub = session.declare_publisher(RAW_THR_DONE,
                                             congestion_control=zenoh.CongestionControl.BLOCK)
        count = [0]

        def on_lat(sample: zenoh.Sample) -> None:
            echo_pub.put(sample.payload)

        def on_thr(sample: zenoh.Sample) -> None:
            if len(sample.payload) <= 8:  # end marker
                done_pub.put(count[0].to_bytes(8, "little"))
                count[0] = 0
            else:
                count[0] += 1

        raw_subs = [session.declare_subscriber(RAW_LAT, on_lat),
                    session.declare_subscriber(RAW_THR, on_thr)]
        # bus: echo pings, count bulk messages
        pings = bus.subscribe(keys.topic_key(TEAM, 0, keys.PING))
        bulk = bus.subscribe(keys.topic_key(TEAM, 0, BULK))

        async def echo() -> None:
            async for msg in pings:
                await bus.publish(bus.key(keys.PING), Ping(
                    robot=1, nonce=msg.nonce, sent_ns=msg.sent_ns, echo=True, payload=msg.payload))

        async def counter() -> None:
            n = 0
            async for msg in bulk:
                if isinstance(msg, Heartbeat):
                    await bus.publish(bus.key(BULK), Heartbeat(robot=1, keyframes=n, status="n"))
                    n = 0
                else:
                    n += 1

        tasks = [asyncio.create_task(echo()), asyncio.create_task(counter())]
        await bus.announce()
        await bus.wait_for_peers({0}, timeout=30)
        await bus.wait_for_absent({0}, timeout=600)  # the parent leaves when it is done
        for t in tasks:
            t.cancel()
        for s in raw_subs:
            s.undeclare()


# ---------------------------------------------------------------------------- parent (measuring)
class Parent:
    def __init__(self, bus: ZenohBus) -> None:
        self.bus = bus
        s = bus.session
        block = zenoh.CongestionControl.BLOCK
        self.raw_lat_pub = s.declare_publisher(RAW_LAT, congestion_control=block)
        self.raw_thr_pub = s.declare_publisher(RAW_THR, congestion_control=block)
        self.raw_echo = s.declare_subscriber(RAW_LAT_ECHO, zenoh.handlers.FifoChannel(1024))
        self.raw_done = s.declare_subscriber(RAW_THR_DONE, zenoh.handlers.FifoChannel(16))
        self.echoes = bus.subscribe(keys.topic_key(TEAM, 1, keys.PING))
        self.counts = bus.subscribe(keys.topic_key(TEAM, 1, BULK))

    # raw ------------------------------------------------------------------------------
    def raw_latency(self, payload: bytes, n: int) -> list[int]:
        out = []
        for _ in range(n):
            t0 = time.perf_counter_ns()
            self.raw_lat_pub.put(payload)
            self.raw_echo.recv()
            out.append(time.perf_counter_ns() - t0)
        return out

    def raw_throughput(self, payload: bytes, n: int) -> tuple[float, int]:
        t0 = time.perf_counter()
        for _ in range(n):
            self.raw_thr_pub.put(payload)
        self.raw_thr_pub.put(b"end")
        got = int.from_bytes(self.raw_done.recv().payload.to_bytes(), "little")
        return got / (time.perf_counter() - t0), got

    # bus ------------------------------------------------------------------------------
    async def bus_latency(self, payload: np.ndarray, n: int) -> list[int]:
        out = []
        key = self.bus.key(keys.PING)
        for i in range(n):
            t0 = time.perf_counter_ns()
            await self.bus.publish(key, Ping(robot=0, nonce=i, sent_ns=t0, payload=payload))
            msg = await self.echoes.recv(timeout=10)
            out.append(time.perf_counter_ns() - t0)
            assert msg.nonce == i and msg.payload.size == payload.size
        return out

    async def bus_throughput(self, payload: np.ndarray, n: int) -> tuple[float, int]:
        key = self.bus.key(BULK)
        t0 = time.perf_counter()
        for i in range(n):
            await self.bus.publish(key, Ping(robot=0, nonce=i, sent_ns=0, payload=payload))
        await self.bus.publish(key, Heartbeat(robot=0, keyframes=n, status="end"))
        got = (await self.counts.recv(timeout=60)).keyframes
        return got / (time.perf_counter() - t0), got


async def measure(args: argparse.Namespace) -> dict[str, Any]:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    bus = ZenohBus(TEAM, 0, listen=[endpoint], block_on_congestion=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.Popen(
        [sys.executable, __file__, "--child", "--connect", endpoint,
         "--queue-size", str(max(args.thr_1k, args.thr_100k) + 16)],
        env=env,
    )
    try:
        async with bus:
            parent = Parent(bus)
            await bus.announce()
            await bus.wait_for_peers({1}, timeout=30)
            for key in (bus.key(keys.PING), bus.key(BULK)):
                await bus.wait_for_subscribers(key, timeout=30)
            await _wait_raw_ready(parent)
            results = {}
            for label, size in SIZES.items():
                n_thr = args.thr_1k if size < 10_000 else args.thr_100k
                results[label] = await _one_size(parent, size, args.lat, n_thr, args.repeat)
                results[label]["wire_bytes"] = {
                    "raw": size,
                    "bus": len(bus.codec.encode(Ping(robot=0, nonce=0, sent_ns=0,
                                                     payload=np.zeros(size, np.uint8)))),
                }
            counters = bus.counters.snapshot()
    finally:
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    met = all(r["throughput_ratio"] >= 0.5 and r["p50_latency_ratio"] <= 2.0
              for r in results.values())
    return {
        "benchmark": "comms",
        "transport": "zenoh tcp 127.0.0.1, peer mode, two processes",
        "zenoh": _zenoh_version(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "repeat": args.repeat,
        "results": results,
        "targets": {"throughput_ratio_min": 0.5, "p50_latency_ratio_max": 2.0, "met": met},
        "bus_counters_parent": counters,
    }


def _zenoh_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("eclipse-zenoh")
    except PackageNotFoundError:
        return "unknown"


async def _wait_raw_ready(parent: Parent) -> None:
    """Ping the child's raw echo until it answers (its declarations have propagated)."""
    deadline = time.monotonic() + 30
    answered = False
    while not answered:
        if time.monotonic() > deadline:
            raise TimeoutError("the raw echo never answered")
        parent.raw_lat_pub.put(b"x" * 16)
        for _ in range(40):
            if parent.raw_echo.try_recv() is not None:
                answered = True
                break
            await asyncio.sleep(0.005)
    await asyncio.sleep(0.3)  # let late echoes of earlier pings arrive, then discard them
    while parent.raw_echo.try_recv() is not None:
        pass


async def _one_size(parent: Parent, size: int, n_lat: int, n_thr: int, repeat: int) -> dict:
    raw_payload = bytes(np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8))
    bus_payload = np.frombuffer(raw_payload, np.uint8).copy()
    # warm up both paths
    parent.raw_latency(raw_payload, 20)
    await parent.bus_latency(bus_payload, 20)
    raw_lat: list[int] = []
    bus_lat: list[int] = []
    raw_thr, bus_thr = [], []
    raw_got, bus_got = [], []
    for _ in range(repeat):  # interleave so that machine noise hits both alike
        raw_lat += parent.raw_latency(raw_payload, n_lat)
        bus_lat += await parent.bus_latency(bus_payload, n_lat)
        rate, got = parent.raw_throughput(raw_payload, n_thr)
        raw_thr.append(rate)
        raw_got.append(got)
        rate, got = await parent.bus_throughput(bus_payload, n_thr)
        bus_thr.append(rate)
        bus_got.append(got)
    raw = {"latency_rtt": percentiles(raw_lat),
           "throughput_msgs_s": statistics.median(raw_thr),
           "throughput_runs": raw_thr, "delivered": raw_got, "sent_per_run": n_thr}
    bus = {"latency_rtt": percentiles(bus_lat),
           "throughput_msgs_s": statistics.median(bus_thr),
           "throughput_runs": bus_thr, "delivered": bus_got, "sent_per_run": n_thr}
    for r in (raw, bus):
        r["throughput_MB_s"] = r["throughput_msgs_s"] * size / 1e6
    return {
        "payload_bytes": size,
        "raw": raw,
        "bus": bus,
        "throughput_ratio": bus["throughput_msgs_s"] / raw["throughput_msgs_s"],
        "p50_latency_ratio": bus["latency_rtt"]["p50_us"] / raw["latency_rtt"]["p50_us"],
        "p99_latency_ratio": bus["latency_rtt"]["p99_us"] / raw["latency_rtt"]["p99_us"],
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print the full JSON result")
    p.add_argument("--lat", type=int, default=500, help="round trips per repeat")
    p.add_argument("--thr-1k", type=int, default=20_000, help="1 KB messages per repeat")
    p.add_argument("--thr-100k", type=int, default=2_000, help="100 KB messages per repeat")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--queue-size", type=int, default=100_000, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        asyncio.run(child(args.connect, args.queue_size))
        return
    result = asyncio.run(measure(args))
    if args.json:
        print(json.dumps(result, indent=2))
        return
    for label, r in result["results"].items():
        print(f"{label:>6}: throughput bus/raw = {r['bus']['throughput_msgs_s']:.0f}/"
              f"{r['raw']['throughput_msgs_s']:.0f} msg/s ({r['throughput_ratio']:.2f}x), "
              f"p50 rtt bus/raw = {r['bus']['latency_rtt']['p50_us']:.0f}/"
              f"{r['raw']['latency_rtt']['p50_us']:.0f} us ({r['p50_latency_ratio']:.2f}x)")
    print("targets met" if result["targets"]["met"] else "targets NOT met")


if __name__ == "__main__":
    main()
