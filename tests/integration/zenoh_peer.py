"""A robot process for the subprocess test: joins over Zenoh, pings its peer, echoes its pings.

Usage: python zenoh_peer.py --robot R --peer P (--listen EP | --connect EP) [--count N] [--last]
Prints one JSON line with what it received, then exits 0.

Shutdown: the ``--last`` robot, once it has every ping and echo, says "done" and waits until
the peer has left; the other robot leaves after it has everything and has heard "done".
So neither closes while the other still needs something from it.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import time

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.messages.team import Heartbeat, Ping
from kimera_multi_py.comms.zenoh_bus import ZenohBus


async def run(args: argparse.Namespace) -> dict:
    bus = ZenohBus("t0", args.robot, robots={args.robot, args.peer}, listen=args.listen or (),
                   connect=args.connect or (), config_file=args.zenoh_config)
    async with bus:
        pings_sub = bus.subscribe(keys.topic_key("t0", args.peer, keys.PING))
        done_sub = bus.subscribe(keys.topic_key("t0", args.peer, keys.HEARTBEAT))
        await bus.announce()
        await bus.wait_for_peers({args.peer}, timeout=10)
        await bus.wait_for_subscribers(bus.key(keys.PING), timeout=10)
        await bus.wait_for_subscribers(bus.key(keys.HEARTBEAT), timeout=10)
        await handshake(bus, args.robot, done_sub)
        pings: list[int] = []
        pongs: list[int] = []
        for i in range(args.count):
            await bus.publish(bus.key(keys.PING),
                              Ping(robot=args.robot, nonce=i, sent_ns=time.monotonic_ns()))
        while len(pings) < args.count or len(pongs) < args.count:
            msg = await pings_sub.recv(timeout=10)
            if msg.echo:
                pongs.append(msg.nonce)
            else:
                pings.append(msg.nonce)
                await bus.publish(bus.key(keys.PING), Ping(robot=args.robot, nonce=msg.nonce,
                                                           sent_ns=msg.sent_ns, echo=True))
        if args.last:
            await bus.publish(bus.key(keys.HEARTBEAT),
                              Heartbeat(robot=args.robot, keyframes=0, status="done"))
            await bus.wait_for_absent({args.peer}, timeout=10)
        else:
            while (await done_sub.recv(timeout=10)).status != "done":
                pass  # late hellos
        return {"robot": args.robot, "pings": pings, "pongs": pongs,
                "counters": bus.counters.snapshot()}


async def handshake(bus: ZenohBus, robot: int, heartbeats, timeout: float = 20.0) -> None:
    """Say hello until each side has heard the other and been heard (an ack).

    Zenoh can lose the first publications on a fresh route even after the publisher sees a
    matching subscriber (see ``conftest._route_ready``); the test counts every ping exactly.
    """
    heard = acked = False
    deadline = time.monotonic() + timeout
    while not (heard and acked):
        if time.monotonic() > deadline:
            raise TimeoutError("handshake with the peer failed")
        status = "hello-ack" if heard else "hello"
        await bus.publish(bus.key(keys.HEARTBEAT), Heartbeat(robot=robot, keyframes=0, status=status))
        try:
            while True:
                msg = await heartbeats.recv(timeout=0.2)
                heard = heard or msg.status in ("hello", "hello-ack")
                acked = acked or msg.status == "hello-ack"
        except TimeoutError:
            pass
    # both routes have carried a message: this ack gets through
    await bus.publish(bus.key(keys.HEARTBEAT), Heartbeat(robot=robot, keyframes=0, status="hello-ack"))


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--robot", type=int, required=True)
    p.add_argument("--peer", type=int, required=True)
    p.add_argument("--listen", action="append")
    p.add_argument("--connect", action="append")
    p.add_argument("--zenoh-config")
    p.add_argument("--count", type=int, default=20)
    p.add_argument("--last", action="store_true")
    print(json.dumps(asyncio.run(run(p.parse_args()))), flush=True)


if __name__ == "__main__":
    main()
