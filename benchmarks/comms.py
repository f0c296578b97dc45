"""ZenohBus between two processes against raw zenoh-python, same payloads, same sessions, same run.

For 1 KB and 100 KB application payloads it measures, for the raw baseline and for the bus alike:

- latency: sequential round trips (ping -> echo -> back), timed at the sender; raw and bus
  blocks of ``--lat-block`` round trips alternate ``--lat-blocks`` times, so machine noise hits
  both alike; p50/p99 over all samples (after ``--warmup`` discarded round trips each);
- throughput: the sender publishes N messages back to back (congestion control BLOCK, so
  nothing is dropped), then an end marker; the receiver counts what it delivers to the
  application and times it from the first delivered message to the end marker: messages/s
  *at the receiver* (``throughput_msgs_s``, the ratio's basis). The sender's end-to-end rate
  (first put to the count coming back) is reported too. Runs alternate raw/bus ``--repeat``
  times after one discarded warm-up run each; medians are reported.

The raw baseline is zenoh-python as its own examples use it (``z_ping``/``z_pong``,
``z_pub_thr``/``z_sub_thr``): a prebuilt ``bytes`` payload put on a declared publisher, the echo
and the count done in the subscriber callback on Zenoh's callback thread, the ping's echo read
with a blocking ``FifoChannel.recv``. The ZenohBus side does everything the system does, per
message: build a typed ``Ping`` (validated) carrying the same payload bytes, encode it into the
envelope, coalesce bursts into batch puts (``ZenohBus.publish``), hand each sample to asyncio,
decode and validate every message, deliver it through a ``Subscription``, and (for echoes)
build and encode a reply. The bus's wire payload is larger by its envelope (``wire_bytes``); the
application payload is the same. Both run over the same pair of sessions (the bus's own) on the
same event loop (``event_loop``: uvloop when installed, else asyncio; ``--loop`` forces one).

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

from kimera_multi_py.comms import keys, runtime
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.comms.zenoh_bus import ZenohBus

REPO = Path(__file__).resolve().parents[1]
TEAM = "bench"
RAW_LAT, RAW_LAT_ECHO = "bench_raw/lat", "bench_raw/lat_echo"
RAW_THR, RAW_THR_DONE = "bench_raw/thr", "bench_raw/thr_done"
# decomposition baselines (reported, not the target's basis): what the bus's architecture costs
# before any of its own work. "copy": the receiving callback copies the payload out of Zenoh
# (what any consumer of the bytes needs); "hop": the callback hands the payload to the asyncio
# loop (call_soon_threadsafe, one drain per burst, as ZenohBus does), which copies it and counts
# (or echoes it, for latency; the echo comes back through the same hop).
FLOORS = ("copy", "hop")
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
        loop = asyncio.get_running_loop()
        # (messages, first arrival in ns) per counting mode
        counts = {mode: [0, 0] for mode in ("raw", *FLOORS)}

        def arrived(mode: str, n: int) -> None:
            count = counts[mode]
            if n <= 8:  # end marker: report count and receiver-side time
                elapsed = time.perf_counter_ns() - count[1]
                done_pub.put(count[0].to_bytes(8, "little") + elapsed.to_bytes(8, "little"))
                count[0] = 0
            else:
                if not count[0]:
                    count[1] = time.perf_counter_ns()
                count[0] += 1

        def on_lat(sample: zenoh.Sample) -> None:
            echo_pub.put(sample.payload)

        def on_thr(sample: zenoh.Sample) -> None:
            arrived("raw", len(sample.payload))

        def on_copy(sample: zenoh.Sample) -> None:
            arrived("copy", len(sample.payload.to_bytes()))

        hop_inbox: list[Any] = []
        hop_pending = [False]
        hop_echo = session.declare_publisher(f"{RAW_LAT}_hop_echo",
                                             congestion_control=zenoh.CongestionControl.BLOCK)

        def hop_drain() -> None:
            hop_pending[0] = False
            items = hop_inbox[:]
            hop_inbox.clear()
            for kind, payload in items:
                data = payload.to_bytes()
                if kind == "lat":
                    hop_echo.put(data)
                else:
                    arrived("hop", len(data))

        def hop(kind: str) -> Any:
            def on_sample(sample: zenoh.Sample) -> None:
                hop_inbox.append((kind, sample.payload))
                if not hop_pending[0]:
                    hop_pending[0] = True
                    loop.call_soon_threadsafe(hop_drain)
            return on_sample

        raw_subs = [session.declare_subscriber(RAW_LAT, on_lat),
                    session.declare_subscriber(RAW_THR, on_thr),
                    session.declare_subscriber(f"{RAW_THR}_copy", on_copy),
                    session.declare_subscriber(f"{RAW_THR}_hop", hop("thr")),
                    session.declare_subscriber(f"{RAW_LAT}_hop", hop("lat"))]
        # bus: echo pings, count bulk messages (the same work as the raw callbacks)
        pings = bus.subscribe(keys.topic_key(TEAM, 0, keys.PING))
        bulk = bus.subscribe(keys.topic_key(TEAM, 0, BULK))

        async def echo() -> None:
            async for msg in pings:
                await bus.publish(bus.key(keys.PING), Ping(
                    robot=1, nonce=msg.nonce, sent_ns=msg.sent_ns, echo=True, payload=msg.payload))

        async def counter() -> None:
            n = first = 0
            async for msg in bulk:
                if isinstance(msg, Heartbeat):  # end marker
                    elapsed = time.perf_counter_ns() - first
                    await bus.publish(bus.key(BULK), Ping(robot=1, nonce=n, sent_ns=elapsed))
                    n = 0
                else:
                    if not n:
                        first = time.perf_counter_ns()
                    n += 1

        tasks = [asyncio.create_task(echo()), asyncio.create_task(counter())]
        await bus.announce()
        await bus.wait_for_peers({0}, timeout=30)
        await bus.wait_for_absent({0}, timeout=600)  # the parent leaves when it is done
        for t in tasks:
            t.cancel()
        for s in raw_subs:
            s.undeclare()
        hop_echo.undeclare()


# ---------------------------------------------------------------------------- parent (measuring)
class Parent:
    def __init__(self, bus: ZenohBus) -> None:
        self.bus = bus
        s = bus.session
        block = zenoh.CongestionControl.BLOCK
        self.raw_lat_pub = s.declare_publisher(RAW_LAT, congestion_control=block)
        self.raw_thr_pub = s.declare_publisher(RAW_THR, congestion_control=block)
        self.raw_echo = s.declare_subscriber(RAW_LAT_ECHO, zenoh.handlers.FifoChannel(1024))
        self.floor_thr_pubs = {mode: s.declare_publisher(f"{RAW_THR}_{mode}", congestion_control=block)
                               for mode in FLOORS}
        self.hop_lat_pub = s.declare_publisher(f"{RAW_LAT}_hop", congestion_control=block)
        self._hop_waiter: asyncio.Future[None] | None = None
        loop = asyncio.get_running_loop()

        def on_hop_echo(sample: zenoh.Sample) -> None:  # the parent's side of the hop
            payload = sample.payload
            loop.call_soon_threadsafe(self._hop_echoed, payload)

        self.hop_echo = s.declare_subscriber(f"{RAW_LAT}_hop_echo", on_hop_echo)
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

    def _hop_echoed(self, payload: zenoh.ZBytes) -> None:
        payload.to_bytes()
        waiter, self._hop_waiter = self._hop_waiter, None
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def hop_latency(self, payload: bytes, n: int) -> list[int]:
        """Round trips through an asyncio hop on each side (no codec, no validation)."""
        loop = asyncio.get_running_loop()
        out = []
        for _ in range(n):
            t0 = time.perf_counter_ns()
            waiter = self._hop_waiter = loop.create_future()
            self.hop_lat_pub.put(payload)
            await asyncio.wait_for(waiter, 10)
            out.append(time.perf_counter_ns() - t0)
        return out

    def raw_throughput(self, payload: bytes, n: int, mode: str = "raw") -> dict[str, float]:
        pub = self.raw_thr_pub if mode == "raw" else self.floor_thr_pubs[mode]
        t0 = time.perf_counter_ns()
        for _ in range(n):
            pub.put(payload)
        pub.put(b"end")
        report = self.raw_done.recv().payload.to_bytes()
        return _rates(int.from_bytes(report[:8], "little"), int.from_bytes(report[8:], "little"),
                      time.perf_counter_ns() - t0)

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

    async def bus_throughput(self, payload: np.ndarray, n: int) -> dict[str, float]:
        key = self.bus.key(BULK)
        t0 = time.perf_counter_ns()
        for i in range(n):
            await self.bus.publish(key, Ping(robot=0, nonce=i, sent_ns=0, payload=payload))
        await self.bus.publish(key, Heartbeat(robot=0, keyframes=n, status="end"))
        report = await self.counts.recv(timeout=60)
        return _rates(report.nonce, report.sent_ns, time.perf_counter_ns() - t0)


def _rates(delivered: int, receiver_ns: int, sender_ns: int) -> dict[str, float]:
    return {"delivered": delivered, "receiver_msgs_s": delivered / max(receiver_ns, 1) * 1e9,
            "end_to_end_msgs_s": delivered / sender_ns * 1e9}


async def measure(args: argparse.Namespace) -> dict[str, Any]:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    bus = ZenohBus(TEAM, 0, listen=[endpoint], block_on_congestion=True)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO), *filter(None, [os.environ.get("PYTHONPATH")])])}
    proc = subprocess.Popen(
        [sys.executable, __file__, "--child", "--connect", endpoint, "--loop", args.loop,
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
            await _wait_bus_ready(parent)
            results = {}
            for label, size in SIZES.items():
                if args.sizes and label not in args.sizes:
                    continue
                n_thr = args.thr_1k if size < 10_000 else args.thr_100k
                results[label] = await _one_size(parent, size, n_thr, args)
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
        "zenoh": _version("eclipse-zenoh"),
        "python": platform.python_version(),
        "event_loop": runtime.loop_name(args.loop),
        "cpus": os.cpu_count(),
        "method": {
            "latency": "round trip timed at the sender; raw and bus blocks alternate",
            "throughput": "messages delivered to the application / receiver-side time from the "
                          "first delivered message to the end marker; median of runs",
            "payload": "same application bytes; raw puts them as is, the bus wraps them in a "
                       "typed Ping and its envelope (see wire_bytes)",
            "warmup": {"round_trips": args.warmup, "throughput_runs": 1},
            "lat_blocks": args.lat_blocks, "lat_block": args.lat_block, "repeat": args.repeat,
        },
        "results": results,
        "targets": {"throughput_ratio_min": 0.5, "p50_latency_ratio_max": 2.0, "met": met},
        "bus_counters_parent": counters,
    }


def _version(dist: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(dist)
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


async def _wait_bus_ready(parent: Parent) -> None:
    """Make both bus routes carry a message before measuring: Zenoh can lose the first
    publications on a fresh route even after the publisher sees a matching subscriber."""
    bus = parent.bus
    for key, sub, probe in (
        (bus.key(keys.PING), parent.echoes, lambda: Ping(robot=0, nonce=0, sent_ns=0)),
        (bus.key(BULK), parent.counts, lambda: Heartbeat(robot=0, keyframes=0, status="end")),
    ):
        deadline = time.monotonic() + 30
        while True:
            await bus.publish(key, probe())
            try:
                await sub.recv(timeout=0.2)
                break
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the bus echo never answered on {key}") from None
        await asyncio.sleep(0.3)  # late answers to earlier probes
        while sub.pending():
            await sub.recv()


async def _one_size(parent: Parent, size: int, n_thr: int, args: argparse.Namespace) -> dict:
    raw_payload = bytes(np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8))
    bus_payload = np.frombuffer(raw_payload, np.uint8).copy()
    # warm up both paths alike
    parent.raw_latency(raw_payload, args.warmup)
    await parent.bus_latency(bus_payload, args.warmup)
    parent.raw_throughput(raw_payload, max(n_thr // 4, 1))
    await parent.bus_throughput(bus_payload, max(n_thr // 4, 1))
    raw_lat: list[int] = []
    bus_lat: list[int] = []
    for _ in range(args.lat_blocks):  # alternate so that machine noise hits both alike
        raw_lat += parent.raw_latency(raw_payload, args.lat_block)
        bus_lat += await parent.bus_latency(bus_payload, args.lat_block)
    raw_runs, bus_runs = [], []
    floor_runs: dict[str, list[dict[str, float]]] = {mode: [] for mode in FLOORS}
    for _ in range(args.repeat):
        raw_runs.append(parent.raw_throughput(raw_payload, n_thr))
        bus_runs.append(await parent.bus_throughput(bus_payload, n_thr))
        if args.floors:
            for mode in FLOORS:
                floor_runs[mode].append(parent.raw_throughput(raw_payload, n_thr, mode))
    raw = _side(raw_lat, raw_runs, n_thr, size)
    bus = _side(bus_lat, bus_runs, n_thr, size)
    floors: dict[str, Any] = {}
    if args.floors:
        await parent.hop_latency(raw_payload, args.warmup)
        hop_lat: list[int] = []
        for _ in range(args.lat_blocks // 3 or 1):
            hop_lat += await parent.hop_latency(raw_payload, args.lat_block)
        hop_p50 = percentiles(hop_lat)["p50_us"]
        for mode in FLOORS:
            rate = statistics.median(r["receiver_msgs_s"] for r in floor_runs[mode])
            floors[mode] = {"throughput_msgs_s": rate,
                            "throughput_ratio": rate / raw["throughput_msgs_s"]}
        floors["hop"]["latency_rtt"] = percentiles(hop_lat)
        floors["hop"]["p50_latency_ratio"] = hop_p50 / raw["latency_rtt"]["p50_us"]
    return {
        "payload_bytes": size,
        "raw": raw,
        "bus": bus,
        "floors": floors,
        "throughput_ratio": bus["throughput_msgs_s"] / raw["throughput_msgs_s"],
        "end_to_end_throughput_ratio": bus["end_to_end_msgs_s"] / raw["end_to_end_msgs_s"],
        "p50_latency_ratio": bus["latency_rtt"]["p50_us"] / raw["latency_rtt"]["p50_us"],
        "p99_latency_ratio": bus["latency_rtt"]["p99_us"] / raw["latency_rtt"]["p99_us"],
    }


def _side(lat: list[int], runs: list[dict[str, float]], n_thr: int, size: int) -> dict[str, Any]:
    rate = statistics.median(r["receiver_msgs_s"] for r in runs)
    return {"latency_rtt": percentiles(lat),
            "throughput_msgs_s": rate,
            "throughput_MB_s": rate * size / 1e6,
            "end_to_end_msgs_s": statistics.median(r["end_to_end_msgs_s"] for r in runs),
            "throughput_runs": [r["receiver_msgs_s"] for r in runs],
            "delivered": [int(r["delivered"]) for r in runs], "sent_per_run": n_thr}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", action="store_true", help="print the full JSON result")
    p.add_argument("--lat-blocks", type=int, default=15, help="alternating latency blocks")
    p.add_argument("--lat-block", type=int, default=100, help="round trips per block and side")
    p.add_argument("--warmup", type=int, default=100, help="discarded round trips per side")
    p.add_argument("--thr-1k", type=int, default=20_000, help="1 KB messages per repeat")
    p.add_argument("--thr-100k", type=int, default=2_000, help="100 KB messages per repeat")
    p.add_argument("--repeat", type=int, default=5, help="throughput runs per side")
    p.add_argument("--no-floors", dest="floors", action="store_false",
                   help="skip the decomposition baselines (raw + copy, raw + asyncio hop)")
    p.add_argument("--sizes", nargs="*", choices=list(SIZES), help="only these payload sizes")
    p.add_argument("--loop", choices=runtime.LOOPS, default="auto",
                   help="event loop: uvloop when installed (auto), or force one")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--queue-size", type=int, default=100_000, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        runtime.run(child(args.connect, args.queue_size), args.loop)
        return
    result = runtime.run(measure(args), args.loop)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    for label, r in result["results"].items():
        print(f"{label:>6}: throughput bus/raw = {r['bus']['throughput_msgs_s']:.0f}/"
              f"{r['raw']['throughput_msgs_s']:.0f} msg/s ({r['throughput_ratio']:.2f}x), "
              f"p50 rtt bus/raw = {r['bus']['latency_rtt']['p50_us']:.0f}/"
              f"{r['raw']['latency_rtt']['p50_us']:.0f} us ({r['p50_latency_ratio']:.2f}x)")
        if r["floors"]:
            f = r["floors"]
            print(f"{'':8}floors: raw+copy {f['copy']['throughput_ratio']:.2f}x, raw+hop "
                  f"{f['hop']['throughput_ratio']:.2f}x throughput; raw+hop p50 rtt "
                  f"{f['hop']['latency_rtt']['p50_us']:.0f} us ({f['hop']['p50_latency_ratio']:.2f}x)")
    print("targets met" if result["targets"]["met"] else "targets NOT met")


if __name__ == "__main__":
    main()
