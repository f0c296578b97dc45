"""What every command shares: the consoles, logging set-up, one-line errors and the result tables."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table

from kimera_multi_py.core.errors import ConfigError, KimeraMultiError

console = Console()
err_console = Console(stderr=True)

ConfigFile = Annotated[Path | None, typer.Option("--config", help="YAML or TOML configuration (e.g. a run folder's "
                                                                  "config.yaml); flags given override it.")]
Truth = Annotated[list[Path] | None, typer.Option("--truth", help="With recorded data: TUM file of a robot's true "
                                                  "base poses, one per robot in order (default: the bags' "
                                                  "ground-truth topic, if any).")]
BagConfig = Annotated[Path | None, typer.Option("--bag-config", help="With recorded data: topics, frames and classes "
                                                "of the bags (TOML or YAML; docs/bags.md); default: each bag's own "
                                                "BAG.toml, else ROS conventions.")]

LinkBudgetOption = Annotated[float | None, typer.Option(
    "--link-budget", metavar="KBPS", help="kB/s per peer link (a token bucket in the bus; PGO and loop-closure "
                                          "traffic first, then objects, then map evidence); default unlimited.")]


def setup_logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s [%(robot)s] %(name)s: %(message)s")

    def default_robot(record: logging.LogRecord) -> bool:
        if not hasattr(record, "robot"):  # records logged without extra={"robot": ...}
            record.robot = "-"
        return True

    for handler in logging.getLogger().handlers:
        handler.addFilter(default_robot)


def fail(exc: KimeraMultiError) -> typer.Exit:
    """Print one line for a library error and return the exit to raise."""
    err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
    return typer.Exit(code=1)


def results_table(res: dict) -> Table:
    table = Table(title=f"{res['scenario']} - mode {res['mode']} - seed {res['seed']}")
    for col in ("robot", "keyframes", "length [m]", "ATE RMSE [m]"):
        table.add_column(col, justify="right")
    for r in res["robots"]:
        table.add_row(str(r["id"]), str(r["keyframes"]), f"{r['trajectory_length_m']:.1f}", f"{r['ate_rmse_m']:.3f}")
    team = res["team"]
    table.add_row("team", str(team["keyframes"]), f"{team['trajectory_length_m']:.1f}", f"{team['ate_rmse_m']:.3f}",
                  style="bold")
    return table


def robot_at(spec: str, option: str) -> tuple[int, float]:
    """``I@T`` as ``(robot, seconds)``."""
    try:
        robot, at = spec.split("@")
        return int(robot), float(at)
    except ValueError:
        raise ConfigError(option, f"expected I@T (robot@seconds), got {spec!r}") from None


def overrides(**sections: Any) -> dict[str, Any]:
    """The flags given on the command line as configuration overrides: ``None`` means not given,
    and sections (dicts keyed by field name) left empty are dropped; a value that is itself a
    mapping (``join``: robot -> seconds) is kept as given."""
    out: dict[str, Any] = {}
    for name, value in sections.items():
        if isinstance(value, dict) and all(isinstance(k, str) for k in value):
            value = overrides(**value) or None
        if value is not None:
            out[name] = value
    return out


def agreement(res: dict) -> None:
    """Whether the robots' team maps agree, and what a robot that stopped waiting was missing."""
    mc = res.get("map_consensus")
    if not mc:
        return
    ref = next(k for k in mc if k.startswith("identical_to_robot"))
    cells = ", ".join(f"robot {r} {v:.3f}" for r, v in mc[ref].items())
    console.print(f"team maps agree: {'yes' if mc.get('agree') else 'NO'} (cells {ref.replace('_', ' ')}: {cells})")
    for r, rep in sorted((res.get("linger") or {}).items()):
        if rep.get("checked") and not rep.get("whole"):
            console.print(f"robot {r} stopped waiting after {rep['waited_s']:.0f} s; missing: {rep['missing']}")


def summary(res: dict) -> None:
    """Loop closures, objects and bytes of a team run, in two lines."""
    if "loop_closures" not in res:
        return
    lc = res["loop_closures"]
    if "true_accepted_inter" in lc:
        console.print(
            f"loop closures: {lc['candidates']} candidates, {lc['verified']} verified, "
            f"{lc['accepted_inter']} inter-robot accepted ({lc['true_accepted_inter']} true, "
            f"{lc['false_accepted_inter']} false; PCM rejected {lc['rejected_pcm_false_inter']} false, "
            f"GNC rejected {lc['rejected_gnc_false_inter']} false)")
    else:  # recorded data without truth: nothing to tell true from false
        console.print(f"loop closures: {lc['accepted_inter']} inter-robot accepted")
    ob = res.get("objects")
    objects = (f"objects: precision {ob['precision']:.2f}, recall {ob['recall']:.2f}, "
               f"centroid error {ob['mean_error']:.2f} m; ") if ob else ""
    console.print(f"{objects}bytes sent {res['bytes_sent']['total']:,}")
