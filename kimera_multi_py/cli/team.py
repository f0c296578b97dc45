"""CLI commands that run the team as processes: ``agent``, ``server``, ``router``, ``launch``, ``record``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.live import Live
from rich.table import Table

from kimera_multi_py.cli.common import BagConfig, ConfigFile, LinkBudgetOption, Truth
from kimera_multi_py.core.errors import ConfigError, KimeraMultiError
from kimera_multi_py.core.ids import MAX_AGENT_ID

Connect = Annotated[list[str] | None, typer.Option("--connect", help="Zenoh endpoint to connect to (repeatable).")]
Listen = Annotated[list[str] | None, typer.Option("--listen", help="Zenoh endpoint to listen on (repeatable).")]
ZenohConfig = Annotated[Path | None, typer.Option("--zenoh-config", help="Zenoh JSON5 config (TLS, auth, ...).")]
Team = Annotated[str, typer.Option("--team", help="Team id: teams on one network never mix.")]
LingerMax = Annotated[float, typer.Option("--linger-max", help="After the final epoch, wait at most this many "
                                                                  "seconds for the team map to be whole.")]
Verbose = Annotated[bool, typer.Option("--verbose", "-v")]
MapMode = Annotated[str | None, typer.Option("--map-consensus", help="off, roam, exact (the default) or laplacian.")]
PgoPeriod = Annotated[float | None, typer.Option(help="Team-time seconds between PGO epochs (default 60).")]


def _rate(value: str) -> float:
    try:
        rate = float(value)
    except ValueError:
        raise typer.BadParameter(f"not a number: {value!r}") from None
    if not rate > 0:
        raise typer.BadParameter("must be > 0 (inf: as fast as possible)")
    return rate


def _connection(team: str, connect: list[str] | None, listen: list[str] | None, zenoh_config: Path | None,
                mode: str | None = None):  # noqa: ANN202 - keeps zenoh out of the CLI's import time
    from kimera_multi_py.team.process import Connection

    if not connect and not listen and zenoh_config is None:
        raise typer.BadParameter("give --connect, --listen or --zenoh-config (multicast scouting is off)")
    return Connection(team, tuple(connect or ()), tuple(listen or ()), str(zenoh_config) if zenoh_config else None,
                      mode)


def register(app: typer.Typer) -> None:
    from kimera_multi_py.cli.common import console, fail, overrides, setup_logging

    @app.command()
    def agent(
        robot: Annotated[int, typer.Option("--robot", help=f"This robot's id (0..{MAX_AGENT_ID}).")],
        source: Annotated[str, typer.Option("--source", help="sim:SCENARIO[:SEED], bag:PATH[:CONFIG] or a "
                                                                          "recorded folder.")],
        out: Annotated[Path, typer.Option("--out", help="Run folder; outputs go to OUT/robotI/.")],
        connect: Connect = None, listen: Listen = None, zenoh_config: ZenohConfig = None, team: Team = "t0",
        rate: Annotated[str, typer.Option(help="Pace keyframes at RATE x their stamps; inf: no pacing.")] = "inf",
        checkpoint_every: Annotated[float, typer.Option(
            help="Seconds between checkpoints (at least: longer once one would take over 5 % of the CPU).")] = 10.0,
        resume: Annotated[bool, typer.Option("--resume", help="Restore OUT/robotI/checkpoint.kmc.")] = False,
        linger_max: LingerMax = 60.0,
        centralized: Annotated[bool | None, typer.Option("--centralized/--distributed", help="A server optimises "
                                                         "the team (default: the configuration's mode, else "
                                                         "distributed).")] = None,
        pgo_period: PgoPeriod = None,
        map_consensus: MapMode = None,
        link_budget: LinkBudgetOption = None,
        config: ConfigFile = None,
        verbose: Verbose = False,
    ) -> None:
        """Run one robot: its keyframes, loop closures, distributed PGO, team map and outputs."""
        from kimera_multi_py.team.config import load_config
        from kimera_multi_py.team.process import AgentJob, run_agent

        setup_logging(verbose)
        try:
            mode = None if centralized is None else "centralized" if centralized else "distributed"
            settings = load_config(config, overrides(run={"mode": mode}, schedule={"period": pgo_period},
                                                     node={"map_consensus": map_consensus,
                                                           "link_budget": link_budget}))
            conn = _connection(team, connect, listen, zenoh_config, "client" if connect and not listen else None)
            summary = run_agent(AgentJob(robot, source, out, conn, _rate(rate), checkpoint_every, resume, settings,
                                         linger_max))
        except KimeraMultiError as exc:
            raise fail(exc) from None
        console.print(f"robot {summary['robot']}: {summary['keyframes']} keyframes, {summary['epochs']} PGO epochs, "
                      f"{summary['wall_s']:.1f} s; wrote {out / f'robot{robot}'}")

    @app.command()
    def server(
        out: Annotated[Path, typer.Option("--out", help="Run folder; the server writes OUT/server/.")],
        connect: Connect = None, listen: Listen = None, zenoh_config: ZenohConfig = None, team: Team = "t0",
        pgo_period: Annotated[float | None, typer.Option(help="Team-time seconds between solves (default 60).")]
        = None,
        config: ConfigFile = None,
        verbose: Verbose = False,
    ) -> None:
        """Centralised mode: optimise the whole team's graph and send each robot its poses."""
        from kimera_multi_py.team.config import load_config
        from kimera_multi_py.team.process import ServerJob, run_server

        setup_logging(verbose)
        try:
            settings = load_config(config, overrides(schedule={"period": pgo_period}))
            conn = _connection(team, connect, listen, zenoh_config, "client" if connect and not listen else None)
            summary = run_server(ServerJob(out, conn, settings))
        except KimeraMultiError as exc:
            raise fail(exc) from None
        console.print(f"server: {summary['solves']} solves over {summary['poses']} poses")

    @app.command()
    def router(
        listen: Annotated[list[str], typer.Option("--listen", help="Endpoint to listen on (repeatable).")],
        zenoh_config: ZenohConfig = None, verbose: Verbose = False,
    ) -> None:
        """A Zenoh router in this process (no zenohd needed), until interrupted."""
        from kimera_multi_py.team.process import run_router

        setup_logging(verbose)
        try:
            run_router(listen, str(zenoh_config) if zenoh_config else None)
        except KimeraMultiError as exc:
            raise fail(exc) from None

    @app.command()
    def launch(
        scenario: Annotated[Path | None, typer.Argument(help="Scenario TOML file (default: the configuration's, "
                                                             "else sims/office.toml).")] = None,
        robots: Annotated[int | None, typer.Option("--robots", "-n", help="Team size (default 3).")] = None,
        seed: Annotated[int | None, typer.Option(help="Random seed (default 0).")] = None,
        mode: Annotated[str | None, typer.Option(help="distributed (the default) or centralized.")] = None,
        out: Annotated[Path, typer.Option()] = Path("runs/launch"),
        rate: Annotated[str, typer.Option(help="Pace keyframes at RATE x their stamps; inf: no pacing.")] = "inf",
        kill: Annotated[list[str] | None, typer.Option("--kill", help="I@T: SIGKILL agent I at stream time T, "
                                                                       "then restart it with --resume.")] = None,
        join: Annotated[list[str] | None, typer.Option("--join", help="I@T: start agent I once the team's "
                                                                       "stream reaches T s.")] = None,
        checkpoint_every: Annotated[float, typer.Option(
            help="Seconds between agent checkpoints (at least: longer once one takes over 5 % of the CPU).")] = 5.0,
        pgo_period: PgoPeriod = None,
        timeout: Annotated[float, typer.Option(help="Give up after this many seconds.")] = 1800.0,
        map_consensus: MapMode = None,
        restart_router: Annotated[list[str] | None, typer.Option("--restart-router", help="T: SIGKILL the router "
                                                                  "at team stream time T and start it again "
                                                                  "(repeatable).")] = None,
        partition: Annotated[list[str] | None, typer.Option("--partition", help="'A,B|C@T0:T1': cut the router "
                                                             "links of the robots outside robot 0's group "
                                                             "from team stream time T0 to T1 (repeatable).")]
        = None,
        tls: Annotated[bool, typer.Option("--tls", help="Mutual TLS: a new team CA and certificates in "
                                                        "OUT/certs; no process without one can join.")] = False,
        linger_max: LingerMax = 60.0,
        source: Annotated[list[str] | None, typer.Option("--source", help="Recorded data instead of a scenario: "
                                                         "bag:PATH[:CONFIG] or a recorded folder, one per robot "
                                                         "in id order; one bag with /robotN namespaces is the "
                                                         "whole team (docs/bags.md).")] = None,
        truth: Truth = None,
        bag_config: BagConfig = None,
        link_budget: LinkBudgetOption = None,
        config: ConfigFile = None,
        verbose: Verbose = False,
    ) -> None:
        """Start a router and N agent processes (and the server) on 127.0.0.1, then evaluate.
        The team runs a scenario, or recorded data (--source: ROS bags or recorded folders)."""
        from kimera_multi_py.cli.common import agreement, results_table, robot_at, summary
        from kimera_multi_py.comms.faults import parse_partition
        from kimera_multi_py.team.config import load_config
        from kimera_multi_py.team.launcher import launch, launch_job, parse_kill, parse_restart, recorded_team

        setup_logging(verbose)
        try:
            if source and (scenario is not None or seed is not None):
                raise ConfigError("--source", "recorded data replaces the scenario: give --source or a scenario "
                                              "and --seed, not both")
            if (truth or bag_config) and not source:
                raise ConfigError("--truth", "--truth and --bag-config go with --source")
            recorded = {"sources": list(source), "truth": list(truth or []), "bag_config": bag_config} \
                if source else {}
            run = {"scenario": scenario, "robots": robots, "seed": seed, "mode": mode,
                   "join": dict(robot_at(j, "join") for j in join) if join else None,
                   "faults": {"partitions": [parse_partition(p) for p in partition] if partition else None}}
            settings = load_config(config, overrides(run=run, schedule={"period": pgo_period},
                                                     node={"map_consensus": map_consensus,
                                                           "link_budget": link_budget}))
            job = launch_job(settings, out, rate=_rate(rate), kills=[parse_kill(k) for k in kill or []],
                             checkpoint_every=checkpoint_every, timeout=timeout, verbose=verbose, tls=tls,
                             router_restarts=[parse_restart(t) for t in restart_router or []], linger_max=linger_max,
                             **recorded)
            if job.sources:
                recorded_team(job)  # bad data: one line before the live table and any process
            with Live(_table({}), console=console, refresh_per_second=4, transient=False) as live:
                results = launch(job, lambda views: live.update(_table(views)))
        except KimeraMultiError as exc:
            raise fail(exc) from None
        res = results.to_dict()
        console.print(results_table(res))
        summary(res)
        agreement(res)
        console.print(f"launch wall {res['wall_s']:.1f} s; wrote {out / 'results.json'}")

    @app.command()
    def certs(
        folder: Annotated[Path, typer.Argument(help="Folder for ca.pem, ca.key and NAME.pem + NAME.key.")],
        robots: Annotated[int, typer.Option("--robots", "-n", help="Certificates for robot0..robotN-1.")] = 3,
        days: Annotated[int, typer.Option(help="Days the certificates are valid.")] = 365,
        team: Team = "t0",
    ) -> None:
        """Make a team CA and a certificate per robot (plus server, router, observer) for mutual TLS;
        the router's config lets each certificate publish only under its own id."""
        from kimera_multi_py.team.certs import make_certs, team_names, write_team_configs

        try:
            idents = make_certs(folder, team_names(robots), days)
            write_team_configs(folder, idents, team)
        except KimeraMultiError as exc:
            raise fail(exc) from None
        console.print(f"wrote a team CA and {len(idents)} certificates to {folder} (ca.key signs new ones: keep "
                      f"it off the robots); give each process --zenoh-config {folder}/NAME.json5 and "
                      f"tls/HOST:PORT endpoints")

    @app.command()
    def record(
        scenario: Annotated[Path, typer.Argument(help="Scenario TOML file.")] = Path("sims/office.toml"),
        robots: Annotated[int | None, typer.Option("--robots", "-n")] = None,
        seed: Annotated[int | None, typer.Option()] = None,
        out: Annotated[Path, typer.Option(help="The recorded folder (or bag) to write.")] = Path("runs/recording"),
        fmt: Annotated[str, typer.Option("--format", help="npz (a recorded folder), ros1 (OUT.bag) or ros2 "
                                                          "(a bag folder); bags get their config as OUT.toml.")]
        = "npz",
        camera: Annotated[bool, typer.Option("--camera", help="Bags: depth + semantic images + CameraInfo "
                                                              "instead of a PointCloud2 with a class field.")] = False,
        label_encoding: Annotated[str, typer.Option("--label-encoding", help="With --camera: mono8, mono16, "
                                                    "rgb8 or bgr8 (colours: a colour table OUT.colours.csv).")]
        = "mono16",
        float64: Annotated[bool, typer.Option("--float64", help="Bags: FLOAT64 cloud fields, 64FC1 depth "
                                                                "(lossless; default float32).")] = False,
    ) -> None:
        """Write the simulator's keyframe streams as a recorded folder or a ROS bag (ground truth apart)."""
        from kimera_multi_py.sim.scenario import load_scenario

        try:
            cfg = load_scenario(scenario, robots=robots)
            if fmt == "npz":
                from kimera_multi_py.sim.source import write_recording

                write_recording(out, cfg, robots=len(cfg.robots), seed=seed, scenario_path=scenario)
            elif fmt in ("ros1", "ros2"):
                from kimera_multi_py.sim.bag_recording import write_bag

                config = write_bag(out, cfg, fmt, seed=seed, camera=camera,  # type: ignore[arg-type]
                                   label_encoding=label_encoding, scenario_path=scenario, float64=float64)
                console.print(f"wrote {config} (the bag's topics, frames and classes)")
            else:
                raise ConfigError("format", f"expected npz, ros1 or ros2, got {fmt!r}")
        except KimeraMultiError as exc:
            raise fail(exc) from None
        console.print(f"wrote {out}")


def _table(views: dict) -> Table:  # type: ignore[type-arg]
    table = Table(title="team")
    for col in ("process", "keyframes", "stream [s]", "closures", "PGO epochs", "rounds", "bytes sent", "alive",
                "restarts"):
        table.add_column(col, justify="right")
    for name, v in views.items():
        table.add_row(name, str(v.keyframes), f"{v.stamp:.0f}", str(v.closures), str(v.epochs), str(v.rounds),
                      f"{v.bytes_sent:,}", "yes" if v.alive else ("done" if v.exit_code == 0 else "no"),
                      str(v.restarts))
    return table


__all__ = ["register", "math"]
