"""``kimera-multi launch``: a router, N agent processes (plus the server) on 127.0.0.1, a live
table, optional faults (kills with ``--resume`` restarts, router restarts, link partitions through
a :class:`LinkProxy`), optional mutual TLS, and the evaluation of what they wrote.

The launcher is not part of the system: it only starts OS processes that find each other
through the router, watches their :class:`AgentState` messages (as a silent observer that never
announces itself, so it is not a team member) and scores the outputs afterwards.

Its configuration (:func:`launch_job`) goes to ``OUT/config.yaml`` with the run resolved and only
what was set explicitly active, and every process loads it (``--config``); each process writes
the configuration it ran with to its own folder (docs/outputs.md).

On recorded data (``sources``: bags or recorded folders, docs/bags.md) the team is what the
sources hold, each agent reads its own robot's data (``--source bag:PATH[:CONFIG]``), and the
run is scored against the ground truth there is (:func:`~kimera_multi_py.team.evaluate.evaluate_recorded_run`).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from kimera_multi_py.comms import keys, runtime
from kimera_multi_py.comms.loopback import Faults, Partition
from kimera_multi_py.comms.messages.team import AgentState
from kimera_multi_py.comms.team import free_ports
from kimera_multi_py.core.errors import ConfigError, KimeraMultiError
from kimera_multi_py.core.ids import MAX_ROBOTS, OBSERVER_ID
from kimera_multi_py.eval.results import Results
from kimera_multi_py.team.config import CONFIG_NAME, DEFAULT_SCENARIO, KimeraConfig
from kimera_multi_py.team.link_proxy import LinkProxy
from kimera_multi_py.team.process import LINGER_MAX

log = logging.getLogger(__name__)

MODES = ("distributed", "centralized")
LAUNCH_ROBOTS = 3  # team size unless configured
LAUNCH_SEED = 0
ROUTER_UP_S = 120.0  # s: the longest the router may take to start on a loaded machine


@dataclass
class Kill:
    robot: int
    at: float  # the robot's stream time (s)
    done: bool = False
    killed_stream_s: float | None = None  # the robot's stream time when it was killed
    checkpoint: str | None = None  # a copy of its last checkpoint at the kill (OUT/logs/robotI.killed.kmc)
    killed_wall: float | None = None
    absent_seen: bool = False
    rejoin_s: float | None = None  # wall s from the kill until its restarted process was present again

    def report(self) -> dict[str, Any]:
        return {"robot": self.robot, "at": self.at, "killed_stream_s": self.killed_stream_s,
                "checkpoint": self.checkpoint, "rejoin_s": self.rejoin_s}


def parse_kill(spec: str) -> Kill:
    """``I@T``: SIGKILL agent I when its stream reaches T seconds."""
    try:
        robot, at = spec.split("@")
        return Kill(int(robot), float(at))
    except ValueError:
        raise ConfigError("kill", f"expected I@T (robot@seconds), got {spec!r}") from None


@dataclass
class RecordedLaunch:
    """A launch's recorded data, checked before any process starts."""

    specs: list[str]  # each robot's --source
    truth: list[Any]  # per robot its true poses at its keyframes, or None
    keyframes: list[int]
    name: str
    world: Any = None  # the simulated world the data came from (a bag's [origin]), if any
    object_sightings: int = 1


@dataclass
class LaunchJob:
    scenario: Path
    robots: int
    seed: int
    mode: str
    out_dir: Path
    rate: float = math.inf
    kills: list[Kill] = field(default_factory=list)
    joins: dict[int, float] = field(default_factory=dict)  # robot -> team stream time it starts at
    checkpoint_every: float = 5.0
    timeout: float = 1800.0
    team: str = "t0"
    verbose: bool = False
    tls: bool = False  # mutual TLS: certificates of a new team CA in OUT/certs, endpoints tls/localhost
    router_restarts: list[float] = field(default_factory=list)  # team stream times to SIGKILL + restart the router
    partitions: list[Partition] = field(default_factory=list)  # windows in team stream time (see cut_off)
    config: KimeraConfig = field(default_factory=KimeraConfig.defaults)  # every process's parameters
    linger_max: float = LINGER_MAX  # each agent's wait, after its final epoch, for a whole team map
    sources: list[str] = field(default_factory=list)  # recorded data (bag:PATH[:CONFIG], folders); none: sim
    truth: list[Path] = field(default_factory=list)  # a TUM file per robot (with sources)
    bag_config: Path | None = None  # the bags' config unless a spec names one
    agent_sources: list[str] = field(default_factory=list)  # each agent's --source (set by recorded_team)
    recorded: RecordedLaunch | None = None  # the sources, checked (set by recorded_team)


def launch_job(config: KimeraConfig, out_dir: Path, **options: Any) -> LaunchJob:
    """The launch ``config`` describes: its ``run`` section (scenario, robots, seed, mode, join,
    fault partitions) with the launcher's defaults filled in and recorded; ``options`` are the
    :class:`LaunchJob`'s other fields."""
    run = config.run
    faults = run.faults.build()
    if dataclasses.replace(faults, partitions=()) != Faults():
        raise ConfigError("run.faults", "launch cuts router links (partitions) only; drop, delay, jitter, "
                                        "duplicates and reordering need kimera-multi sim")
    if options.get("sources"):  # recorded data: the team's size comes from the sources (launch resolves it)
        mode = run.mode or MODES[0]
        return LaunchJob(Path(), run.robots or 0, 0, mode, Path(out_dir), joins=dict(run.join),
                         partitions=list(faults.partitions), config=config.updated({"run": {"mode": mode}}),
                         **options)
    scenario, robots, mode = run.scenario or DEFAULT_SCENARIO, run.robots or LAUNCH_ROBOTS, run.mode or MODES[0]
    seed = LAUNCH_SEED if run.seed is None else run.seed
    config = config.updated({"run": {"scenario": scenario, "robots": robots, "seed": seed, "mode": mode}})
    return LaunchJob(scenario, robots, seed, mode, Path(out_dir), joins=dict(run.join),
                     partitions=list(faults.partitions), config=config, **options)


@dataclass
class RobotView:
    """What the live table shows of one process."""

    keyframes: int = 0
    stamp: float = 0.0
    epochs: int = 0
    closures: int = 0
    rounds: int = 0
    bytes_sent: int = 0
    alive: bool = False
    finished: bool = False
    restarts: int = 0
    exit_code: int | None = None


class TeamClock:
    """Team stream time, which fault windows are given in: the furthest stream stamp any robot
    has reported while the streams run. Once every robot the router still hears has finished its
    stream, it runs on with the wall clock at the launch's rate (real time when the rate is
    unbounded), so a window can end, and a partition heal, after the streams are over. It never
    runs back (a robot heard again after a cut may report an old stamp)."""

    def __init__(self, rate: float) -> None:
        self.rate = rate if math.isfinite(rate) and rate > 0 else 1.0
        self._over: tuple[float, float] | None = None  # (wall, team time) when the streams ended
        self._last = 0.0

    def now(self, views: dict[str, RobotView], heard: Collection[int], wall: float) -> float:
        stamps = max((v.stamp for v in views.values()), default=0.0)
        robots = [v for name, v in views.items() if name.startswith("robot") and int(name[5:]) in heard]
        if not robots or not all(v.finished for v in robots):
            self._over = None  # a robot still streams (or one heard again has not said it finished)
            self._last = max(self._last, stamps)
        else:
            if self._over is None:
                self._over = (wall, max(self._last, stamps))
            self._last = max(self._last, stamps, self._over[1] + (wall - self._over[0]) * self.rate)
        return self._last


def parse_restart(spec: str) -> float:
    """``T``: SIGKILL the router when the team's stream reaches T seconds, and start it again."""
    try:
        at = float(spec)
    except ValueError:
        raise ConfigError("restart-router", f"expected seconds, got {spec!r}") from None
    if not (math.isfinite(at) and at >= 0):
        raise ConfigError("restart-router", f"expected seconds >= 0, got {spec!r}")
    return at


View = Callable[[dict[str, RobotView]], None]


def recorded_team(job: LaunchJob) -> RecordedLaunch:
    """Open the job's recorded sources (every error a user can fix is raised here: a missing bag,
    a missing topic, a robot without keyframes, more robots asked than the sources hold) and set
    ``job.robots``, ``job.agent_sources``, ``job.recorded`` and the configuration's team size from them."""
    from kimera_multi_py.io.bag.reader import BagSource
    from kimera_multi_py.team.recorded import open_sources

    sources = open_sources(job.sources, job.bag_config)
    try:
        return _recorded_team(job, sources)
    finally:
        for src in sources:
            if isinstance(src, BagSource):
                src.close()


def _recorded_team(job: LaunchJob, sources: list[Any]) -> RecordedLaunch:
    from kimera_multi_py.io.bag.reader import BagSource
    from kimera_multi_py.sim.simulation import Simulation
    from kimera_multi_py.team.build import agent_params, bag_spec
    from kimera_multi_py.team.recorded import recorded_world, source_truth

    held = len(sources)
    if job.robots > held:
        raise ConfigError("robots", f"{job.robots} robots asked, but {' '.join(job.sources)} "
                                    f"hold{'s' * (len(job.sources) == 1)} {held}")
    sources = sources[:job.robots or held]
    specs = []
    for i, src in enumerate(sources):
        spec = job.sources[min(i, len(job.sources) - 1)]
        robot = getattr(src, "robot", i)
        # agent i reads robot i of its source (a bag of one robot: that robot, whatever its namespace)
        if robot != i and not (isinstance(src, BagSource) and held == 1):
            raise ConfigError("--source", f"{spec}: robot {i} of the team would be robot {robot} of the data; "
                                          f"launch needs robots 0..{len(sources) - 1}, or a source per robot")
        if spec.startswith("bag:"):
            path, config = bag_spec(spec)
            config = config or job.bag_config
            spec = f"bag:{path}" + (f":{config}" if config is not None else "")
        specs.append(spec)
    truth = source_truth(sources, job.truth)
    job.robots, job.agent_sources = len(sources), specs
    job.config = job.config.updated({"run": {"robots": job.robots}})
    name = Path(job.sources[0].removeprefix("bag:")).name
    job.recorded = RecordedLaunch(specs, truth, [s.num_keyframes for s in sources], name)
    scenario, seed = recorded_world(sources)
    if scenario is not None and all(t is not None for t in truth):  # simulated data: score against its world
        job.recorded.name, job.recorded.world = scenario.name, Simulation(scenario, seed).world
        job.recorded.object_sightings = agent_params(scenario, job.config).team_object_sightings
    return job.recorded


def launch(job: LaunchJob, on_update: View | None = None) -> Results:
    """Run the team as processes and evaluate it (see the module docstring)."""
    recorded = job.recorded or (recorded_team(job) if job.sources else None)  # fail here, not in N processes
    if job.mode not in MODES:
        raise ConfigError("mode", f"unknown mode {job.mode!r} (available: {', '.join(MODES)})")
    if job.robots < 1 or job.robots > MAX_ROBOTS:
        raise ConfigError("robots", f"must be in 1..{MAX_ROBOTS}, got {job.robots}")
    for k in job.kills:
        if not 0 <= k.robot < job.robots:
            raise ConfigError("kill", f"robot {k.robot} is not in the team of {job.robots}")
    for p in job.partitions:
        bad = sorted(r for g in p.groups for r in g if not 0 <= r < job.robots)
        if bad:
            raise ConfigError("partition", f"robot(s) {bad} are not in the team of {job.robots}")
    for r in job.joins:
        if not 0 <= r < job.robots or len(job.joins) >= job.robots:
            raise ConfigError("join", f"robot {r}: needs a robot of the team, and someone to join")
    from kimera_multi_py.sim.scenario import load_scenario

    cfg = None if recorded else load_scenario(job.scenario, robots=job.robots)  # fail here, not in N processes
    job.config.write(job.out_dir, only_set=True)  # what every process loads
    t0 = time.monotonic()
    runtime.run(_launch(job, on_update))
    from kimera_multi_py.team.evaluate import evaluate_recorded_run, evaluate_run

    if recorded is not None:
        results = evaluate_recorded_run(job.out_dir, recorded.truth, recorded.keyframes, recorded.name, job.mode,
                                        time.monotonic() - t0, recorded.world, recorded.object_sightings)
    else:
        assert cfg is not None
        results = evaluate_run(job.out_dir, cfg, job.seed, job.mode, time.monotonic() - t0, job.config)
    results.write_json(job.out_dir / "results.json")
    return results


def cut_off(p: Partition) -> frozenset[int]:
    """The robots whose router link a partition cuts: all but the group holding robot 0 (else the
    largest group). With one router, robots cut off together cannot reach each other either."""
    home = next((g for g in p.groups if 0 in g), max(p.groups, key=len))
    return frozenset().union(*(g for g in p.groups if g is not home))


def _tls_configs(job: LaunchJob, folder: Path) -> dict[str, Path]:
    """A new team CA and certificates in ``folder``, and each process's ``--zenoh-config`` file."""
    from kimera_multi_py.team.certs import make_certs, team_names, write_team_configs

    return write_team_configs(folder, make_certs(folder, team_names(job.robots)), job.team)


async def _router_up(observer: Any, router: subprocess.Popen[bytes], log_path: Path, cap: float = ROUTER_UP_S) -> None:
    """Until the observer's session is linked to the router (agents connect as clients, which
    fail at once without a router), or :class:`KimeraMultiError` if it exits or ``cap`` passes."""
    deadline = time.monotonic() + cap
    while not list(observer.session.info.routers_zid()):
        if router.poll() is not None:
            raise KimeraMultiError(f"the router exited with code {router.returncode}; see {log_path}")
        if time.monotonic() > deadline:
            raise KimeraMultiError(f"the router did not come up within {cap:.0f} s; see {log_path}")
        await asyncio.sleep(0.1)


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "kimera_multi_py.cli.main", *args]


async def _launch(job: LaunchJob, on_update: View | None) -> None:
    from kimera_multi_py.comms.zenoh_bus import ZenohBus

    out = job.out_dir
    (out / "logs").mkdir(parents=True, exist_ok=True)
    port = free_ports(1)[0]
    endpoint = f"tls/localhost:{port}" if job.tls else f"tcp/127.0.0.1:{port}"
    configs = _tls_configs(job, out / "certs") if job.tls else {}

    def zconf(name: str) -> list[str]:
        return ["--zenoh-config", str(configs[name])] if name in configs else []

    # robots a partition cuts off reach the router through a proxy whose link the launcher cuts
    proxies: dict[int, LinkProxy] = {}
    for r in sorted(frozenset().union(*(cut_off(p) for p in job.partitions))):
        proxies[r] = LinkProxy("127.0.0.1", port)
        await proxies[r].start()
    link_events: list[dict[str, Any]] = []

    def conn(name: str, robot: int | None = None) -> list[str]:
        ep = endpoint if robot not in proxies else endpoint.rsplit(":", 1)[0] + f":{proxies[robot].port}"
        return ["--connect", ep, "--team", job.team, *zconf(name)] + (["-v"] if job.verbose else [])
    procs: dict[str, subprocess.Popen[bytes]] = {}
    logs: list[Any] = []

    def start(name: str, args: list[str]) -> subprocess.Popen[bytes]:
        fh = (out / "logs" / f"{name}.log").open("ab")
        logs.append(fh)
        return subprocess.Popen(_cmd(*args), stdout=fh, stderr=subprocess.STDOUT)

    config = ["--config", str(out / CONFIG_NAME)]

    def agent_args(r: int, resume: bool) -> list[str]:
        source = job.agent_sources[r] if job.agent_sources else f"sim:{job.scenario}:{job.seed}"
        args = ["agent", "--robot", str(r), "--source", source,
                "--out", str(out), "--rate", str(job.rate), "--checkpoint-every", str(job.checkpoint_every),
                "--linger-max", str(job.linger_max),
                "--centralized" if job.mode == "centralized" else "--distributed", *config, *conn(f"robot{r}", r)]
        return args + (["--resume"] if resume else [])

    views = {f"robot{r}": RobotView() for r in range(job.robots)}
    if job.mode == "centralized":
        views["server"] = RobotView()
    observer: ZenohBus | None = None
    pending_restarts = sorted(job.router_restarts)
    restarted: list[dict[str, float]] = []
    try:
        procs["router"] = start("router", ["router", "--listen", endpoint, *zconf("router")])
        await asyncio.sleep(0.5)
        observer = ZenohBus(job.team, OBSERVER_ID, connect=[endpoint],
                            config_file=configs.get("observer"))
        await _router_up(observer, procs["router"], out / "logs" / "router.log")
        (out / "logs" / "endpoint").write_text(endpoint + "\n")  # the router is up: where tools connect
        states = observer.subscribe(keys.topic_all(job.team, keys.AGENT_STATE))
        if job.mode == "centralized":
            procs["server"] = start("server", ["server", "--out", str(out), *config, *conn("server")])
        for r in range(job.robots):
            if r not in job.joins:
                procs[f"robot{r}"] = start(f"robot{r}", agent_args(r, False))
        deadline = time.monotonic() + job.timeout
        clock = TeamClock(job.rate)
        while True:
            while (msg := states.try_recv()) is not None:
                if isinstance(msg, AgentState) and msg.robot < job.robots:
                    v = views[f"robot{msg.robot}"]
                    v.keyframes, v.stamp, v.epochs, v.finished = msg.keyframes, msg.stamp, msg.epoch, msg.finished
                    v.closures, v.rounds, v.bytes_sent = msg.closures, msg.rounds, msg.bytes_sent
            team_time = clock.now(views, observer.peers(), time.monotonic())
            while pending_restarts and team_time >= pending_restarts[0]:
                at = pending_restarts.pop(0)
                router = procs["router"]
                os.kill(router.pid, signal.SIGKILL)
                router.wait()
                log.warning("killed the router at team time %.1f s (restart at %.1f s); starting it again",
                            team_time, at)
                procs["router"] = start("router", ["router", "--listen", endpoint, *zconf("router")])
                restarted.append({"at": at, "team_time_s": team_time})
            for r, proxy in proxies.items():
                cut = any(p.start <= team_time < p.end and r in cut_off(p) for p in job.partitions)
                if cut != proxy.is_cut:
                    if cut:
                        proxy.cut()
                    else:
                        proxy.restore()
                    log.warning("robot %d's link %s at team time %.1f s", r, "cut" if cut else "restored", team_time)
                    link_events.append({"robot": r, "cut": cut, "team_time_s": team_time, "absent_seen": False})
                elif cut and r not in observer.peers():
                    last = next(e for e in reversed(link_events) if e["robot"] == r)
                    last["absent_seen"] = True  # the team really lost it
            for r, at in job.joins.items():
                if f"robot{r}" not in procs and team_time >= at:
                    log.warning("robot %d joins at team time %.1f s", r, team_time)
                    procs[f"robot{r}"] = start(f"robot{r}", agent_args(r, False))
            peers = observer.peers()
            for r in range(job.robots):
                views[f"robot{r}"].alive = r in peers
            for k in job.kills:
                if k.killed_wall is not None and k.rejoin_s is None:
                    k.absent_seen = k.absent_seen or k.robot not in peers
                    if k.absent_seen and k.robot in peers:
                        k.rejoin_s = round(time.monotonic() - k.killed_wall, 2)
            for k in job.kills:
                p = procs.get(f"robot{k.robot}")
                if p is not None and not k.done and views[f"robot{k.robot}"].stamp >= k.at and p.poll() is None:
                    os.kill(p.pid, signal.SIGKILL)
                    p.wait()
                    k.done, k.killed_wall = True, time.monotonic()
                    k.killed_stream_s = views[f"robot{k.robot}"].stamp
                    ckpt = out / f"robot{k.robot}" / "checkpoint.kmc"
                    if ckpt.exists():  # what the restart must not lose
                        k.checkpoint = str(shutil.copy(ckpt, out / "logs" / f"robot{k.robot}.killed.kmc"))
                    log.warning("killed robot %d at stream time %.1f s; restarting with --resume", k.robot,
                                views[f"robot{k.robot}"].stamp)
                    views[f"robot{k.robot}"].restarts += 1
                    procs[f"robot{k.robot}"] = start(f"robot{k.robot}", agent_args(k.robot, True))
            for name, p in procs.items():
                if name in views:
                    views[name].exit_code = p.poll()
            if on_update is not None:
                on_update(views)
            team = [p for n, p in procs.items() if n != "router"]
            codes = [p.poll() for p in team] + [None] * sum(f"robot{r}" not in procs for r in job.joins)
            if any(c not in (None, 0) for c in codes):
                bad = [n for n, p in procs.items() if n != "router" and p.poll() not in (None, 0)]
                raise KimeraMultiError(f"{bad[0]} exited with code {procs[bad[0]].poll()}; "
                                       f"see {out / 'logs' / (bad[0] + '.log')}")
            if all(c == 0 for c in codes):
                break
            if time.monotonic() > deadline:
                raise KimeraMultiError(f"the team did not finish within {job.timeout:.0f} s; logs in {out / 'logs'}")
            await asyncio.sleep(0.1)
    finally:
        (out / "faults.json").write_text(json.dumps({"kills": [k.report() for k in job.kills],
                                                     "router_restarts": restarted, "links": link_events}, indent=2))
        for proxy in proxies.values():
            await proxy.close()
        if observer is not None:
            await observer.close()
        for p in procs.values():
            if p.poll() is None:
                p.terminate()
        for p in procs.values():
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        for fh in logs:
            fh.close()
