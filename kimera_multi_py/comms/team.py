"""A team's buses in one process: a loopback network, or one Zenoh session per robot on 127.0.0.1,
fully meshed with explicit endpoints (docs/deployment.md)."""

from __future__ import annotations

import contextlib
import socket
from collections.abc import AsyncIterator, Sequence

from kimera_multi_py.comms.bus import Bus
from kimera_multi_py.comms.loopback import Faults, LoopbackNetwork
from kimera_multi_py.comms.zenoh_bus import ZenohBus
from kimera_multi_py.core.errors import ConfigError

TRANSPORTS = ("loopback", "zenoh")


def free_ports(count: int) -> list[int]:
    """``count`` TCP ports free on 127.0.0.1 right now."""
    socks, ports = [], []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
            ports.append(s.getsockname()[1])
    finally:
        for s in socks:
            s.close()
    return ports


@contextlib.asynccontextmanager
async def zenoh_buses(robots: Sequence[int], team: str = "pgo",
                      timeout: float = 10.0) -> AsyncIterator[list[Bus]]:
    """Open one peer session per robot (each listens, and connects to every lower id)."""
    ports = free_ports(len(robots))
    endpoints = [f"tcp/127.0.0.1:{p}" for p in ports]
    buses: list[ZenohBus] = []
    try:
        for n, robot in enumerate(robots):
            buses.append(ZenohBus(team, robot, robots=robots, listen=[endpoints[n]],
                                  connect=endpoints[:n]))
        for bus in buses:
            await bus.announce()
        for bus in buses:
            await bus.wait_for_peers([r for r in robots if r != bus.robot], timeout)
        yield list(buses)
    finally:
        for bus in buses:
            await bus.close()


@contextlib.asynccontextmanager
async def open_buses(robots: Sequence[int], transport: str = "loopback", drop: float = 0.0,
                     seed: int = 0, team: str = "pgo") -> AsyncIterator[list[Bus]]:
    """One bus per robot: an in-process loopback network, or one Zenoh session per robot."""
    if transport == "loopback":
        net = LoopbackNetwork(team=team, seed=seed, faults=Faults(drop=drop), robots=robots)
        buses: list[Bus] = [net.bus(r) for r in robots]
        try:
            yield buses
        finally:
            for b in buses:
                await b.close()
    elif transport == "zenoh":
        async with zenoh_buses(robots, team=team) as zbuses:
            yield zbuses
    else:
        raise ConfigError("transport", f"must be one of {TRANSPORTS}, got {transport!r}")
