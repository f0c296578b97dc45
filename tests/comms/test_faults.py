"""Fault schedules from CLI specs: partition parsing, the links cut at a time, and the sim's Faults."""

import asyncio
import math

import pytest

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.faults import boundaries, check_robots, cut_links, parse_partition, sim_faults
from kimera_multi_py.comms.loopback import LoopbackNetwork
from kimera_multi_py.comms.messages.team import Heartbeat
from kimera_multi_py.core.errors import ConfigError


def test_a_partition_spec_names_its_groups_and_window():
    p = parse_partition("0,1|2@60:120")
    assert p.groups == (frozenset({0, 1}), frozenset({2}))
    assert (p.start, p.end) == (60.0, 120.0)
    assert parse_partition(" 3|1,2|0 @0:").end == math.inf


@pytest.mark.parametrize("spec", ["0,1|2", "0,1|2@60", "0,1@60:120", "0,1|x@1:2", "0|1@5:5", "0|1@-1:5",
                                  "0|1@a:b", "0,1|1@0:1", "|1@0:1", "0|-2@0:1", "0|1@nan:5"])
def test_a_bad_partition_spec_is_refused_with_the_spec_named(spec):
    with pytest.raises(ConfigError, match="partition"):
        parse_partition(spec)


def test_the_links_cut_follow_the_window():
    parts = [parse_partition("0,1|2@60:120"), parse_partition("0|1@100:110")]
    robots = [0, 1, 2, 3]
    assert cut_links(parts, robots, 59.9) == frozenset()
    assert cut_links(parts, robots, 60.0) == {(0, 2), (1, 2)}
    assert cut_links(parts, robots, 105.0) == {(0, 1), (0, 2), (1, 2)}  # robot 3 is in no group
    assert cut_links(parts, robots, 120.0) == frozenset()
    assert boundaries(parts) == [60.0, 100.0, 110.0, 120.0]


def test_a_partition_must_name_robots_of_the_team():
    check_robots([parse_partition("0,1|2@1:2")], range(3))
    with pytest.raises(ConfigError, match=r"\[3\]"):
        check_robots([parse_partition("0,1|3@1:2")], range(3))


def test_sim_faults_converts_milliseconds_and_checks_values():
    f = sim_faults(drop=0.2, delay_ms=30, jitter_ms=5, partitions=["0|1@1:2"])
    assert (f.drop, f.delay, f.jitter) == (0.2, 0.03, 0.005)
    assert f.partitions[0].groups == (frozenset({0}), frozenset({1}))
    for bad in ({"delay_ms": -1}, {"jitter_ms": math.inf}, {"drop": 1.5}):
        with pytest.raises(ConfigError):
            sim_faults(**bad)  # type: ignore[arg-type]


def test_a_parsed_partition_cuts_loopback_traffic_on_the_network_clock():
    """The spec drives the loopback network: inside the window nothing crosses, after it all does."""
    t = [0.0]

    async def run() -> list[int]:
        net = LoopbackNetwork(seed=0, faults=sim_faults(partitions=["0|1@10:20"]), clock=lambda: t[0])
        a, b = net.bus(0), net.bus(1)
        sub = b.subscribe(keys.topic_all(b.team, keys.HEARTBEAT))
        got = []
        for now in (5.0, 10.0, 19.9, 20.0):
            t[0] = now
            await a.publish(a.key(keys.HEARTBEAT), Heartbeat(robot=0, keyframes=int(now)))
            await net.settle()
            msg = sub.try_recv()
            got.append(-1 if msg is None else msg.keyframes)
        await a.close()
        await b.close()
        return got

    assert asyncio.run(run()) == [5, -1, -1, 20]
