"""The ``kimera-multi`` command line. Library errors become one line on stderr and exit code 1."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from kimera_multi_py.cli.common import (
    ConfigFile,
    LinkBudgetOption,
    console,
    err_console,
    fail,
    overrides,
    results_table,
    robot_at,
    setup_logging,
    summary,
)
from kimera_multi_py.core.errors import ConfigError, KimeraMultiError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="kimera-multi-py: multi-robot distributed metric-semantic SLAM.")


@app.callback()
def _root() -> None:
    """kimera-multi-py: multi-robot distributed metric-semantic SLAM."""


@app.command()
def sim(
    scenario: Annotated[Path | None, typer.Argument(help="Scenario TOML file (default: the configuration's, "
                                                         "else sims/office.toml).")] = None,
    robots: Annotated[int | None, typer.Option("--robots", "-n", help="Team size (overrides the file).")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed (overrides the file).")] = None,
    mode: Annotated[str | None, typer.Option(help="odometry (dead reckoning, the default), distributed or "
                                                  "centralized.")] = None,
    transport: Annotated[str | None, typer.Option(help="loopback (in-process, the default) or zenoh (one session "
                                                       "per robot).")] = None,
    out: Annotated[Path, typer.Option(help="Run folder for results.json, config.yaml and trajectories.")]
    = Path("runs/sim"),
    rerun: Annotated[bool, typer.Option("--rerun/--no-rerun", help="Write OUT/recording.rrd.")] = True,
    join: Annotated[list[str] | None, typer.Option("--join", help="I@T: robot I joins T s after the others "
                                                                   "(repeatable).")] = None,
    map_consensus: Annotated[str | None, typer.Option("--map-consensus", help="off, roam, exact (the default) or "
                                                                              "laplacian.")] = None,
    comm_range: Annotated[float | None, typer.Option("--comm-range", help="Radio range (m) for map "
                                                                          "traffic; default unlimited.")] = None,
    drop: Annotated[float | None, typer.Option("--drop", help="Loopback: drop this fraction of messages.")] = None,
    delay: Annotated[float | None, typer.Option("--delay", help="Loopback: delay every message by MS milliseconds "
                                                                "(on the simulation's event time: it orders "
                                                                "deliveries and costs no wall time).")] = None,
    jitter: Annotated[float | None, typer.Option("--jitter", help="Loopback: add uniform +-MS ms to each "
                                                                  "delay.")] = None,
    partition: Annotated[list[str] | None, typer.Option("--partition", help="Loopback: 'A,B|C@T0:T1' cuts robots "
                                                                             "A,B off from C from T0 to T1 s "
                                                                             "(repeatable).")] = None,
    link_budget: LinkBudgetOption = None,
    config: ConfigFile = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Run the multi-robot simulation and evaluate it against ground truth."""
    from kimera_multi_py.comms.faults import parse_partition
    from kimera_multi_py.team.config import load_config
    from kimera_multi_py.viz.rerun_viz import make_viz
    from kimera_multi_py.workflow.simulate import SimRunner

    setup_logging(verbose)
    try:
        faults = {"drop": drop, "delay": _seconds(delay, "delay"), "jitter": _seconds(jitter, "jitter"),
                  "partitions": [parse_partition(p) for p in partition] if partition else None}
        run = {"scenario": scenario, "robots": robots, "seed": seed, "mode": mode, "transport": transport,
               "comm_range": comm_range, "join": dict(robot_at(j, "join") for j in join) if join else None,
               "faults": faults}
        settings = load_config(config, overrides(run=run, node={"map_consensus": map_consensus,
                                                                 "link_budget": link_budget}))
        viz = make_viz(out / "recording.rrd" if rerun else None)
        runner = SimRunner.from_config(settings, out_dir=out, viz=viz)
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), console=err_console, transient=False) as progress:
            task = progress.add_task(f"{runner.cfg.name} x{len(runner.cfg.robots)}", total=None)
            runner.on_progress = lambda done, total: progress.update(task, completed=done, total=total)
            results = runner.run()
    except KimeraMultiError as exc:
        raise fail(exc) from None
    res = results.to_dict()
    console.print(results_table(res))
    summary(res)
    console.print(f"sim {res['sim_seconds']:.1f} s in {res['wall_s']:.2f} s wall "
                  f"(x{res['realtime_factor']:.1f} real time); wrote {out / 'results.json'}")


def _seconds(ms: float | None, option: str) -> float | None:
    """A ``--delay``/``--jitter`` in milliseconds as seconds (None: not given)."""
    if ms is None:
        return None
    if not (math.isfinite(ms) and ms >= 0):
        raise ConfigError(option, f"must be a finite number of milliseconds >= 0, got {ms}")
    return ms / 1000.0


def _register_commands() -> None:
    from kimera_multi_py.cli import config as cli_config
    from kimera_multi_py.cli import team as cli_team
    from kimera_multi_py.cli.pgo import register

    register(app)
    cli_team.register(app)
    cli_config.register(app)
    __import__("kimera_multi_py.cli.scenario", fromlist=["register"]).register(app)
    __import__("kimera_multi_py.cli.query", fromlist=["register"]).register(app)
    __import__("kimera_multi_py.cli.replay", fromlist=["register"]).register(app)


_register_commands()


def main() -> None:
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
