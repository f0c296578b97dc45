"""The ``kimera-multi`` command line. Library errors become one line on stderr and exit code 1."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from kimera_multi_py.cli.common import console, err_console, fail, results_table, robot_at, setup_logging, summary
from kimera_multi_py.core.errors import KimeraMultiError

DEFAULT_SCENARIO = Path("sims/office.toml")

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="kimera-multi-py: multi-robot distributed metric-semantic SLAM.")


@app.callback()
def _root() -> None:
    """kimera-multi-py: multi-robot distributed metric-semantic SLAM."""


@app.command()
def sim(
    scenario: Annotated[Path, typer.Argument(help="Scenario TOML file.")] = DEFAULT_SCENARIO,
    robots: Annotated[int | None, typer.Option("--robots", "-n", help="Team size (overrides the file).")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed (overrides the file).")] = None,
    mode: Annotated[str, typer.Option(help="odometry (dead reckoning), distributed or centralized.")] = "odometry",
    transport: Annotated[str, typer.Option(help="loopback (in-process) or zenoh (one session per robot).")]
    = "loopback",
    out: Annotated[Path, typer.Option(help="Run folder for results.json and trajectories.")] = Path("runs/sim"),
    rerun: Annotated[bool, typer.Option("--rerun/--no-rerun", help="Write OUT/recording.rrd.")] = True,
    join: Annotated[list[str] | None, typer.Option("--join", help="I@T: robot I joins T s after the others "
                                                                   "(repeatable).")] = None,
    map_consensus: Annotated[str, typer.Option("--map-consensus", help="off, roam, exact or laplacian.")] = "exact",
    comm_range: Annotated[float | None, typer.Option("--comm-range", help="Radio range (m) for map "
                                                                          "traffic; default unlimited.")] = None,
    drop: Annotated[float, typer.Option("--drop", help="Loopback: drop this fraction of messages.")] = 0.0,
    delay: Annotated[float, typer.Option("--delay", help="Loopback: delay every message by MS milliseconds "
                                                         "(wall time; the simulated clock waits).")] = 0.0,
    jitter: Annotated[float, typer.Option("--jitter", help="Loopback: add uniform +-MS ms to each delay.")] = 0.0,
    partition: Annotated[list[str] | None, typer.Option("--partition", help="Loopback: 'A,B|C@T0:T1' cuts robots "
                                                                             "A,B off from C from T0 to T1 s "
                                                                             "(repeatable).")] = None,
    verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
) -> None:
    """Run the multi-robot simulation and evaluate it against ground truth."""
    from kimera_multi_py.comms.faults import sim_faults
    from kimera_multi_py.sim.scenario import load_scenario
    from kimera_multi_py.viz.rerun_viz import make_viz
    from kimera_multi_py.workflow.simulate import SimRunner

    setup_logging(verbose)
    try:
        faults = sim_faults(drop, delay, jitter, partition or [])
        cfg = load_scenario(scenario, robots=robots)
        viz = make_viz(out / "recording.rrd" if rerun else None)
        runner = SimRunner(cfg, seed=seed, mode=mode, out_dir=out, viz=viz, transport=transport,
                           join=dict(robot_at(j, "join") for j in join or []), map_consensus=map_consensus,
                           comm_range=comm_range, faults=faults)
        with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                      TimeElapsedColumn(), console=err_console, transient=False) as progress:
            task = progress.add_task(f"{cfg.name} x{len(cfg.robots)}", total=None)
            runner.on_progress = lambda done, total: progress.update(task, completed=done, total=total)
            results = runner.run()
    except KimeraMultiError as exc:
        raise fail(exc) from None
    res = results.to_dict()
    console.print(results_table(res))
    summary(res)
    console.print(f"sim {res['sim_seconds']:.1f} s in {res['wall_s']:.2f} s wall "
                  f"(x{res['realtime_factor']:.1f} real time); wrote {out / 'results.json'}")


def _register_commands() -> None:
    from kimera_multi_py.cli import team as cli_team
    from kimera_multi_py.cli.pgo import register

    register(app)
    cli_team.register(app)
    __import__("kimera_multi_py.cli.scenario", fromlist=["register"]).register(app)
    __import__("kimera_multi_py.cli.query", fromlist=["register"]).register(app)


_register_commands()


def main() -> None:
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
