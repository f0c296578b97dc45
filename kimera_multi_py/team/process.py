"""One robot, the server or a router as an OS process on Zenoh: the workflows behind
``kimera-multi agent``, ``server`` and ``router`` (core → workflow → CLI).

An agent process builds its :class:`Agent` (or restores it from its checkpoint), opens one Zenoh
session, runs its :class:`AgentNode` over keyframes from a source until the team's final
optimisation, and writes ``OUT/robotI/``. Checkpoints go to ``OUT/robotI/checkpoint.kmc`` every
``checkpoint_every`` seconds at most (atomically), and no more often than keeps their CPU within
:data:`CHECKPOINT_SHARE` of the process's (a checkpoint grows with the map: see
:func:`next_checkpoint`); ``resume`` restores the agent and continues its source at the next
keyframe, so a later checkpoint costs recomputation after a kill, never data. Parameters come from the job's
:class:`~kimera_multi_py.team.config.KimeraConfig`; each process writes the configuration it runs
with to ``OUT/robotI/config.yaml`` (``OUT/server/config.yaml``; docs/outputs.md).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import resource
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.checkpoint import load_checkpoint, save_checkpoint
from kimera_multi_py.agent.node import AgentNode
from kimera_multi_py.agent.outputs import outcome_of, own_graph, write_outcome
from kimera_multi_py.comms import runtime
from kimera_multi_py.comms.link_budget import LinkBudget, budget_of
from kimera_multi_py.comms.zenoh_bus import ZenohBus
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.ids import MAX_AGENT_ID, SERVER_ID
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.io.g2o import write_g2o
from kimera_multi_py.io.outdir import ensure_writable
from kimera_multi_py.io.sources import KeyframeSource
from kimera_multi_py.mapping.config import get_submap_map
from kimera_multi_py.mapping.octree_io import export_team_map
from kimera_multi_py.server.node import Server, ServerNode
from kimera_multi_py.team.build import SERVER_ODOM_SIGMAS, params_for, source_from_spec
from kimera_multi_py.team.config import KimeraConfig

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.kmc"
LINGER_NAME = "linger.json"
RESOURCES_NAME = "resources.json"  # the agent process's CPU time and peak memory
LINKS_NAME = "links.json"  # under a link budget: what the robot's links carried (docs/deployment.md, "Link budget")
LINGER_MAX = 60.0  # s: the longest an agent waits, after its final epoch, for the team to be whole


@dataclass
class Connection:
    """How a process joins the team's Zenoh network (the same flags for every process)."""

    team: str = "t0"
    connect: Sequence[str] = ()
    listen: Sequence[str] = ()
    zenoh_config: str | None = None
    mode: str | None = None  # zenoh mode (peer, client, router); default peer without a file

    def bus(self, robot: int, budget: LinkBudget | None = None) -> ZenohBus:
        return ZenohBus(self.team, robot, mode=self.mode, listen=list(self.listen), connect=list(self.connect),
                        config_file=self.zenoh_config, budget=budget)


CHECKPOINT_SHARE = 0.05  # the most of an agent's CPU that checkpoints may take


def next_checkpoint(every: float, cost_s: float, share: float = CHECKPOINT_SHARE) -> float:
    """Seconds until the next checkpoint: ``every``, or longer when the last one took ``cost_s``
    CPU seconds, so that checkpoints take at most ``share`` of the time between them."""
    return max(every, cost_s / share)


@dataclass
class AgentJob:
    robot: int
    source: str  # sim:SCENARIO[:SEED] or a recorded folder
    out_dir: Path
    connection: Connection = field(default_factory=Connection)
    rate: float = math.inf
    checkpoint_every: float = 10.0
    resume: bool = False
    config: KimeraConfig = field(default_factory=KimeraConfig.defaults)  # run.mode: distributed unless centralized
    linger_max: float = LINGER_MAX  # s after the final epoch to wait for a whole team map


def run_agent(job: AgentJob) -> dict[str, Any]:
    """Run one robot to the end of the team's run; return a small summary."""
    return runtime.run(_agent(job))


def checkpoint_path(out_dir: Path, robot: int) -> Path:
    return Path(out_dir) / f"robot{robot}" / CHECKPOINT_NAME


async def _agent(job: AgentJob) -> dict[str, Any]:
    t0 = time.monotonic()
    if job.robot < 0 or job.robot > MAX_AGENT_ID:
        raise ConfigError("robot", f"robot id must be in 0..{MAX_AGENT_ID}, got {job.robot}")
    ckpt = checkpoint_path(job.out_dir, job.robot)
    ensure_writable(ckpt.parent)  # an unwritable or full folder fails here, in one line
    extra: dict[str, Any] = {}
    config = job.config
    if config.run.mode == "odometry":
        raise ConfigError("run.mode", "an agent runs distributed or centralized, not odometry")
    params = params_for(source_from_spec(job.source, job.robot, 0), config)
    if config.run.mode == "centralized":
        params = replace(params, server=SERVER_ID)
    if job.resume and ckpt.exists():
        agent, extra = load_checkpoint(ckpt)
        if agent.robot != job.robot:
            raise ConfigError("resume", f"{ckpt} holds robot {agent.robot}, not robot {job.robot}")
        log.info("robot %d resumes at keyframe %d", job.robot, agent.num_keyframes, extra={"robot": job.robot})
    else:
        agent = Agent(job.robot, None, params)
    start = agent.num_keyframes
    resume = json.loads(extra["source"]) if isinstance(extra.get("source"), str) else None
    source = source_from_spec(job.source, job.robot, start, resume)
    schedule = config.to_schedule(round_timeout=0.5, final_grace=2.0)
    node_params = config.to_node_params(server=params.server, state_period=1.0)
    pgo_params, map_params = config.to_pgo_params(), config.to_map_params()
    run = config.run.model_copy(update={"mode": "centralized" if params.server is not None else "distributed"})
    KimeraConfig.resolved(run, agent.params, pgo_params, node_params, schedule, map_params,
                          config.to_scene_graph_params()).write(ckpt.parent)
    bus = job.connection.bus(job.robot, budget_of(node_params.link_budget, node_params.link_policy))
    node = AgentNode(agent, bus, pgo_params, schedule, node_params, map_params=map_params)
    if node.pgo is not None:
        node.pgo.epoch = node.pgo.completed = int(extra.get("epoch", 0))
    last, wait = time.monotonic(), job.checkpoint_every

    def on_keyframe(kf: KeyframeInput) -> None:
        nonlocal last, wait
        if time.monotonic() - last >= wait:
            cpu = time.process_time()
            save_checkpoint(ckpt, agent, _node_state(node, source))
            last, wait = time.monotonic(), next_checkpoint(job.checkpoint_every, time.process_time() - cpu)

    try:
        await node.start()
        # with map consensus, linger a few map periods so the last evidence is relayed
        await node.run(iter(source), rate=job.rate, on_keyframe=on_keyframe, linger=2.0)
        whole = await until_whole(node, config.run.robots, job.linger_max)
        save_checkpoint(ckpt, agent, _node_state(node, source))
        d = write_outcome(job.out_dir, outcome_of(node), own_graph(agent))
        (d / LINGER_NAME).write_text(json.dumps(whole, indent=1))
        (d / RESOURCES_NAME).write_text(json.dumps(_resources(agent, node), indent=1))
        if bus.budget is not None:
            (d / LINKS_NAME).write_text(json.dumps({"kbps": bus.budget.kbps, "policy": bus.budget.policy,
                                                    "links": bus.link_report()}, indent=1))
        if node.maps is not None:
            export_team_map(node.maps.team_map, d)
    finally:
        await node.close()
        await bus.close()
    return {"robot": job.robot, "keyframes": agent.num_keyframes, "resumed_at": start if job.resume else None,
            "epochs": node.pgo.stats.epochs if node.pgo is not None else 0, "wall_s": time.monotonic() - t0}


def _resources(agent: Agent, node: AgentNode) -> dict[str, Any]:
    """This process's CPU seconds and peak RSS, per second of the robot's stream, and the bytes
    its map stores hold (docs/performance.md)."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    cpu = ru.ru_utime + ru.ru_stime
    stream = agent.stamps[-1] - agent.stamps[0] if len(agent.stamps) > 1 else 0.0
    out: dict[str, Any] = {"cpu_s": round(cpu, 2), "stream_s": round(stream, 2),
                           "cpu_s_per_stream_s": round(cpu / stream, 4) if stream > 0 else None,
                           "peak_rss_mb": round(ru.ru_maxrss / 1024, 1), **node.memory()}
    return out


async def until_whole(node: AgentNode, robots: int | None, cap: float, poll: float = 0.05,
                      settle: float = 2.0) -> dict[str, Any]:
    """After the final epoch, serve the team until this robot's map evidence and pose tables match
    every team robot's last version summary (``mapshare.consensus.MapConsensus.gaps``), no
    epoch runs and no robot present waits on a verification (``AgentState.verifying``), and that
    has held for ``settle`` s (two state periods: a leader that learns of a late closure from a
    robot's state re-runs the final epoch, and a robot gone by then could never match the new
    poses), or for ``cap`` s counted from when no robot present is still streaming (a robot
    whose stream ended first, or that ran a final epoch alone behind a partition, stays for the
    team's final epoch). A robot out of reach whose stream had not ended when last heard also
    holds the wait, within the cap: a partition that heals late brings it back with evidence no
    summary announced yet. ``robots``: the team's size (default: every robot heard of). Returns
    what ``linger.json`` records: whether the team was whole, the wait, what was missing and
    which robots stayed out of reach mid-stream."""
    maps = node.maps
    t0 = time.monotonic()
    if maps is None or maps.mode != "exact":  # no version summaries to compare
        return {"checked": False, "whole": None, "waited_s": 0.0, "missing": {}}

    def team() -> set[int]:
        return set(range(robots)) if robots else maps.heard()

    def busy() -> bool:  # an epoch still running (robots that met late run another final one),
        # the safety net's look at the final frame still to come (it may ask for another), or a
        # robot present still waiting on a verification (a closure of it re-runs the final epoch)
        pgo, alive = node.pgo, node.alive()
        verifying = node.verifying() > 0 or (pgo is not None and any(
            st.verifying > 0 for r, st in pgo.states.items() if r != node.robot and r in alive))
        return (pgo is not None and pgo.busy) or not node.settled or verifying

    def streaming() -> bool:  # a robot still present feeds its stream: the team's run goes on
        pgo, alive = node.pgo, node.alive()
        return pgo is not None and any(not st.finished for r, st in pgo.states.items()
                                       if r != node.robot and r in alive)

    def out_of_reach() -> list[int]:  # gone before its stream ended: it may come back
        pgo, alive = node.pgo, node.alive()
        return [] if pgo is None else sorted(r for r, st in pgo.states.items()
                                             if r != node.robot and r not in alive and not st.finished)

    quiet_since: float | None = None
    start = t0
    while time.monotonic() - start < cap:
        going_on = streaming()
        if going_on:  # the wait is bounded from when no robot present still streams: a robot
            start = time.monotonic()  # whose stream ended first stays for the team's final epoch
        gaps = maps.gaps(team())
        now = time.monotonic()
        if gaps or busy() or going_on or out_of_reach():
            quiet_since = None
        elif quiet_since is None:
            quiet_since = now
        elif now - quiet_since >= settle:
            break
        await node.drain()
        await node.tick()
        await asyncio.sleep(poll)
    gaps, gone = maps.gaps(team()), out_of_reach()
    waited = round(time.monotonic() - t0, 2)
    if gaps:
        log.warning("robot %d: the team map is not whole after %.0f s (--linger-max): %s", node.robot, waited,
                    "; ".join(f"robot {r}: {', '.join(g)}" for r, g in gaps.items()), extra={"robot": node.robot})
    if gone:
        log.warning("robot %d: robot(s) %s out of reach since before their streams ended, after %.0f s "
                    "(--linger-max)", node.robot, ", ".join(map(str, gone)), waited, extra={"robot": node.robot})
    return {"checked": True, "whole": not gaps and not gone, "waited_s": waited, "robots": sorted(team()),
            "missing": {str(r): g for r, g in gaps.items()}, "out_of_reach": gone}


def _node_state(node: AgentNode, source: KeyframeSource) -> dict[str, Any]:
    # the source's state as JSON text: a simulator's generator state holds 128-bit integers
    state = json.dumps(source.state()) if hasattr(source, "state") else None
    return {"epoch": node.pgo.completed if node.pgo is not None else 0, "next_keyframe": node.agent.num_keyframes,
            "source": state}


# ---------------------------------------------------------------------------- server
@dataclass
class ServerJob:
    out_dir: Path
    connection: Connection = field(default_factory=Connection)
    config: KimeraConfig = field(default_factory=KimeraConfig.defaults)


def run_server(job: ServerJob) -> dict[str, Any]:
    return runtime.run(_server(job))


async def _server(job: ServerJob) -> dict[str, Any]:
    config = job.config
    # the closure noise is the agents'; the odometry noise the server's own unless configured
    params = config.to_agent_params(odom_sigmas=SERVER_ODOM_SIGMAS)
    schedule = config.to_schedule(final_grace=2.0)
    map_params = config.to_map_params()
    d = Path(job.out_dir) / "server"
    KimeraConfig.resolved(config.run.model_copy(update={"mode": "centralized"}), params, config.to_pgo_params(),
                          config.to_node_params(), schedule, map_params, config.to_scene_graph_params()).write(d)
    node_params = config.to_node_params()
    bus = job.connection.bus(SERVER_ID, budget_of(node_params.link_budget, node_params.link_policy))
    server = Server(SERVER_ID, None, params.closure_sigmas, params.odom_sigmas, frame_params=config.to_pgo_params())
    node = ServerNode(server, bus, schedule)
    # the agents' map, mapping and PGO parameters (exact fusion; the frame screen faces the maps)
    node.fuse_maps(get_submap_map(params.mapping), params=map_params,
                   keyframes_per_submap=params.mapping.keyframes_per_submap)
    try:
        await node.start()
        await node.run()
    finally:
        await node.close()
        await bus.close()
    if node.maps is not None:
        export_team_map(node.maps.team_map, d)
    if bus.budget is not None:
        (d / LINKS_NAME).write_text(json.dumps({"kbps": bus.budget.kbps, "policy": bus.budget.policy,
                                                "links": bus.link_report()}, indent=1))
    graph, _ = server.graph()
    if graph.num_poses:
        write_g2o(d / "graph.g2o", graph)
    weights = [[a, ka, b, kb, w] for (a, ka, b, kb), w in sorted(server.stats.weights.items())]
    (d / "weights.json").write_text(json.dumps({"version": 1, "weights": weights, "solves": server.stats.solves}))
    return {"solves": server.stats.solves, "poses": server.stats.poses}


# ---------------------------------------------------------------------------- router
def run_router(listen: Sequence[str], zenoh_config: str | None = None, stop: asyncio.Event | None = None) -> None:
    """A Zenoh router inside this process (no ``zenohd`` needed) until interrupted."""
    import zenoh

    from kimera_multi_py.comms.zenoh_bus import zenoh_config as make_config

    # zenoh's own warnings (a refused TLS handshake: "peer sent no certificates", "invalid peer
    # certificate") go to this process's stderr, the router's log under launch; RUST_LOG overrides
    zenoh.init_log_from_env_or("warn")
    conf = make_config("router", listen, (), zenoh_config, False)
    with zenoh.open(conf):
        log.info("router listening on %s", ", ".join(listen))
        try:
            while stop is None or not stop.is_set():
                time.sleep(0.2)
        except KeyboardInterrupt:
            pass
