"""The fault suite's figures, each beside the clean run's, measured in this run.

Loopback simulation of ``sims/faults.toml`` (small's building, shorter and faster routes: 39 s of
stream; seed 0, distributed, exact map consensus, PGO period 20 s), the tests' setting:

* ``clean`` -- the reference: team ATE, map agreement (share of cells identical to the
  centralised fusion, worst robot), false inter-robot closures;
* ``loss`` -- 20 % of messages dropped on every link;
* ``partition`` -- robots {0, 1} cut off from {2} from 10 s to 30 s, then healed: the epochs each
  side began during the cut, and the end figures; ``partition_heals_at_stream_end`` the same
  from 18 s to 38 s, which heals about a second before the streams end (about 39 s);
* ``late_join`` -- robot 2 joins 20 s late (one PGO period): when it was first a PGO member
  (after its join, vs the PGO period) and its closures.

Real Zenoh sessions on 127.0.0.1:

* ``fuzz`` -- N fuzzed and mutated payloads into a live agent's topics: how many were counted,
  by reason, and whether the agent still answers;
* ``second_team`` -- a team ``t1`` robot publishing valid messages on its own keys and on t0's:
  what reached t0, and what t0 counted;
* ``mtls`` -- who can join a mutual-TLS team: a member, a stranger with no certificate, one with
  a certificate of another CA (both trust the team CA).

Processes (``--processes``; ``sims/tiny.toml``, 2 robots at 4x real time): a clean launch,
``--kill 1@40`` (the rejoin time), ``--restart-router 25``, ``--partition 0|1@20:45`` and ``--tls``.

``--scenario sims/small.toml --period 60`` gives the simulation cases on small (the windows and
the join scale with its stream).

    python benchmarks/faults.py --json [--fuzz 10000] [--skip-sim] [--processes]
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.comms import keys
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.faults import sim_faults
from kimera_multi_py.comms.loopback import Faults
from kimera_multi_py.comms.messages.team import AgentState
from kimera_multi_py.comms.team import free_ports
from kimera_multi_py.comms.zenoh_bus import Tls, ZenohBus
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.source import keyframe_input
from kimera_multi_py.team.build import agent_params
from kimera_multi_py.team.certs import make_certs
from kimera_multi_py.workflow.simulate import SimRunner

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # tests.support: the fuzzer is a test helper, not in the package

from tests.support.fuzz import fuzz_payloads, stranger_traffic  # noqa: E402

FAULTS = ROOT / "sims" / "faults.toml"
TINY = ROOT / "sims" / "tiny.toml"
TEAM = "t0"


# ---------------------------------------------------------------------------- simulation
def _sim(scenario: Path, period: float, faults: Faults | None = None, join: dict[int, float] | None = None
         ) -> tuple[SimRunner, dict[str, Any]]:
    t0 = time.perf_counter()
    runner = SimRunner(load_scenario(scenario), seed=0, mode="distributed", faults=faults, join=join,
                       pgo_period=period, quality=False)
    res = runner.run().to_dict()
    lc = res["loop_closures"]
    fig = {"team_ate_m": res["team"]["ate_rmse_m"],
           "map_identical_min": min(a["identical"] for a in res["map_consensus"]["agreement"].values()),
           "accepted_inter": lc["accepted_inter"], "false_accepted_inter": lc["false_accepted_inter"],
           "pgo_epochs": res["pgo_runs"], "wall_s": round(time.perf_counter() - t0, 1)}
    return runner, fig


def sim_cases(scenario: Path, period: float) -> dict[str, Any]:
    """The cases of ``tests/sim/test_faults.py``; the windows scale with the stream (a partition of
    one PGO period from a quarter of the stream; another that heals a second before its end)."""
    duration = Simulation(load_scenario(scenario), 0).duration
    _, clean = _sim(scenario, period)
    out: dict[str, Any] = {"clean": clean}
    runner, loss = _sim(scenario, period, sim_faults(drop=0.2))
    st = runner.nodes[0].bus.network.stats  # type: ignore[attr-defined]
    loss.update(dropped=st.dropped, attempted=st.attempted,
                ate_ratio_to_clean=loss["team_ate_m"] / clean["team_ate_m"])
    out["loss"] = {**loss, "must": "ate_ratio_to_clean <= 1.1 and map_identical_min == 1.0"}
    q = round(duration / 4)
    for name, (start, end) in (("partition", (q, q + period)),
                               ("partition_heals_at_stream_end", (round(duration) - 1 - period, round(duration) - 1))):
        runner, part = _sim(scenario, period, sim_faults(partitions=[f"0,1|2@{start}:{end}"]))
        began = sorted({(h[0], h[1], round(h[3], 1)) for n in runner.nodes for h in n.pgo.history
                        if start <= h[3] < end})
        part.update(window_s=[start, end],
                    partitioned=runner.nodes[0].bus.network.stats.partitioned,  # type: ignore[attr-defined]
                    epochs_during=[{"epoch": e, "members": list(m), "began_s": b} for e, m, b in began],
                    ate_ratio_to_clean=part["team_ate_m"] / clean["team_ate_m"])
        out[name] = {**part, "must": "both sides began epochs during the cut; ATE and agreement as clean"}
    at = period
    runner, late = _sim(scenario, period, join={2: at})
    first = next((h[3] for h in runner.nodes[0].pgo.history if 2 in h[1]), None)
    late.update(join_s=at, first_member_s=first, pgo_period_s=runner.schedule.period,
                in_pgo_within_s=None if first is None else round(first - at, 1))
    out["late_join"] = {**late, "must": "in_pgo_within_s <= pgo_period_s"}
    return out


# ---------------------------------------------------------------------------- zenoh
def _state(stamp: float) -> AgentState:
    return AgentState(robot=1, keyframes=0, stamp=stamp, finished=False, epoch=0, complete=False, closures=0,
                      rounds=0, bytes_sent=0)


async def _wait(cond: Any, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        await asyncio.sleep(0.01)
    return True


def _accepted(bus: ZenohBus) -> int:
    return bus.counters.total("received").messages - bus.counters.total("sent").messages


async def _live_agent(port: int) -> tuple[AgentNode, ZenohBus, asyncio.Task[None], asyncio.Event]:
    cfg = load_scenario(TINY)
    bus = ZenohBus(TEAM, 0, listen=[f"tcp/127.0.0.1:{port}"], queue_size=1_000_000)
    node = AgentNode(Agent(0, None, agent_params(cfg)), bus)
    await node.start()
    for kf in itertools.islice(Simulation(cfg, 0).keyframes(0), 12):
        await node.process_keyframe(keyframe_input(kf))
    stop = asyncio.Event()

    async def loop() -> None:
        while not stop.is_set():
            await node.drain()
            await node.tick()
            await asyncio.sleep(0.002)

    return node, bus, asyncio.create_task(loop()), stop


async def fuzz_case(n: int) -> dict[str, Any]:
    port = free_ports(1)[0]
    node, bus, task, stop = await _live_agent(port)
    async with ZenohBus(TEAM, 1, connect=[f"tcp/127.0.0.1:{port}"]) as fuzzer:
        await fuzzer.wait_for_subscribers(keys.topic_key(TEAM, 1, keys.AGENT_STATE), 5)
        probe = Codec(TEAM, 1).encode(_state(0.0))
        while not _accepted(bus):  # the route carries a message before counting starts
            fuzzer.session.put(keys.topic_key(TEAM, 1, keys.AGENT_STATE), probe)
            await asyncio.sleep(0.1)
        await asyncio.sleep(0.3)
        base_acc, base_drop = _accepted(bus), sum(bus.counters.dropped.values())
        base_err = sum(node.errors.values())
        t0 = time.perf_counter()
        for i, (key, data) in enumerate(fuzz_payloads(TEAM, 1, n, seed=16)):
            fuzzer.session.put(key, data, congestion_control=_BLOCK())
            if i % 200 == 0:
                await asyncio.sleep(0)
        await _wait(lambda: _accepted(bus) - base_acc + sum(bus.counters.dropped.values()) - base_drop >= n, 60)
        await asyncio.sleep(0.5)
        wall = time.perf_counter() - t0
        ok = Codec(TEAM, 1).encode(_state(1e6))
        fuzzer.session.put(keys.topic_key(TEAM, 1, keys.AGENT_STATE), ok)
        answers = await _wait(lambda: node._peer_stamp == 1e6, 10)
    crashed = task.done()
    stop.set()
    await asyncio.wait_for(task, 10)
    await node.close()
    await bus.close()
    accepted = _accepted(bus) - base_acc - 1  # minus the final valid state
    dropped = dict(bus.counters.dropped)
    return {"payloads": n, "counted": accepted + sum(dropped.values()) - base_drop, "accepted": accepted,
            "dropped_by_reason": dropped, "refused_by_node": sum(node.errors.values()) - base_err,
            "agent_crashed": crashed, "agent_answers_after": answers, "wall_s": round(wall, 1),
            "clean": {"payloads": 0, "agent_crashed": False},
            "must": "counted == payloads, agent_crashed false, agent_answers_after true"}


def _BLOCK() -> Any:
    import zenoh

    return zenoh.CongestionControl.BLOCK


async def second_team_case() -> dict[str, Any]:
    port = free_ports(1)[0]
    node, bus, task, stop = await _live_agent(port)
    async with ZenohBus("t1", 1, connect=[f"tcp/127.0.0.1:{port}"]) as other:
        msgs, witness = await stranger_traffic(other, TEAM, _wait)
        await _wait(lambda: bus.counters.dropped.get("team", 0) >= len(msgs), 20)
        await asyncio.sleep(0.3)
        heard_by_t1 = witness.pending()
    stop.set()
    await asyncio.wait_for(task, 10)
    await node.close()
    await bus.close()
    return {"sent_on_own_keys": len(msgs), "heard_by_own_team": heard_by_t1, "sent_on_team0_keys": len(msgs),
            "entered_team0": _accepted(bus), "team0_dropped": dict(bus.counters.dropped),
            "team0_peers": sorted(bus.peers()), "clean": {"entered_team0": 0},
            "must": "entered_team0 == 0 and team0_dropped == {'team': sent_on_team0_keys}"}


async def mtls_case() -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        team = make_certs(Path(tmp) / "team", ["robot0", "robot1"])
        rogue = make_certs(Path(tmp) / "rogue", ["robot2"])
        endpoint = f"tls/localhost:{free_ports(1)[0]}"
        a = ZenohBus(TEAM, 0, listen=[endpoint], tls=Tls(team["robot0"].ca, team["robot0"].cert, team["robot0"].key))
        await a.announce()
        joined: dict[str, bool] = {}
        tries = {"member": Tls(team["robot1"].ca, team["robot1"].cert, team["robot1"].key),
                 "no_certificate": Tls(team["robot0"].ca, mtls=False),
                 "other_ca_certificate": Tls(team["robot0"].ca, rogue["robot2"].cert, rogue["robot2"].key)}
        for robot, (name, tls) in enumerate(tries.items(), start=1):
            async with ZenohBus(TEAM, robot, connect=[endpoint], tls=tls) as c:
                await c.announce()
                joined[name] = await _wait(lambda r=robot: r in a.peers(), 3 if name != "member" else 10)  # type: ignore[misc]
        await a.close()
    return {"joined": joined, "clean": {"joined": {"member": True}},
            "must": "member joins; no_certificate and other_ca_certificate do not"}


# ---------------------------------------------------------------------------- processes
def _launch(out: Path, *extra: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli.main", "launch", str(TINY), "--robots", "2",
                           "--out", str(out), "--rate", "4", "--checkpoint-every", "2", *extra],
                          capture_output=True, text=True, timeout=900, cwd=ROOT)
    fig: dict[str, Any] = {"exit_code": proc.returncode, "wall_s": round(time.perf_counter() - t0, 1)}
    if proc.returncode == 0:
        res = json.loads((out / "results.json").read_text())
        fig.update(keyframes=[r["keyframes"] for r in res["robots"]], pgo_epochs=res["pgo_runs"],
                   team_ate_m=res["team"]["ate_rmse_m"])
        faults = json.loads((out / "faults.json").read_text())
        fig.update({k: v for k, v in faults.items() if v})
    return fig


def process_cases() -> dict[str, Any]:
    """``sims/tiny.toml`` (2 robots, aliased: its ATE is not the point) as processes at 4x real time."""
    with tempfile.TemporaryDirectory() as tmp:
        clean = _launch(Path(tmp) / "clean")
        return {"clean": clean,
                "kill_resume": {**_launch(Path(tmp) / "kill", "--kill", "1@40"),
                                "must": "exit 0, every keyframe, rejoin_s <= 10"},
                "router_restart": {**_launch(Path(tmp) / "router", "--restart-router", "25"),
                                   "must": "exit 0, every keyframe"},
                "partition": {**_launch(Path(tmp) / "partition", "--partition", "0|1@20:45"),
                              "must": "exit 0, every keyframe, robot 1 absent during the cut"},
                "tls": {**_launch(Path(tmp) / "tls", "--tls"), "must": "exit 0, every keyframe"}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print JSON (the only output format)")
    ap.add_argument("--fuzz", type=int, default=10_000, help="fuzzed payloads")
    ap.add_argument("--skip-sim", action="store_true", help="only the Zenoh cases (seconds, not minutes)")
    ap.add_argument("--scenario", type=Path, default=FAULTS, help="scenario of the simulation cases")
    ap.add_argument("--period", type=float, default=20.0, help="PGO period (s) of the simulation cases")
    ap.add_argument("--processes", action="store_true", help="also launch the team as processes: kill + "
                                                             "resume, router restart, mutual TLS")
    args = ap.parse_args()
    out: dict[str, Any] = {"scenario": str(args.scenario), "seed": 0, "pgo_period_s": args.period}
    if not args.skip_sim:
        out.update(sim_cases(args.scenario, args.period))
    out["fuzz"] = asyncio.run(fuzz_case(args.fuzz))
    out["second_team"] = asyncio.run(second_team_case())
    out["mtls"] = asyncio.run(mtls_case())
    if args.processes:
        out["processes"] = process_cases()
    json.dump(out, sys.stdout, indent=2, default=str)
    print()


if __name__ == "__main__":
    main()
