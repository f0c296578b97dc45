"""``kimera-multi replay``: a team on recorded data (ROS bags or recorded folders) in one process."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from kimera_multi_py.cli.common import (
    BagConfig,
    ConfigFile,
    Truth,
    console,
    fail,
    results_table,
    setup_logging,
    summary,
)
from kimera_multi_py.core.errors import KimeraMultiError


def register(app: typer.Typer) -> None:
    @app.command()
    def replay(
        source: Annotated[list[str], typer.Option("--source", help="bag:PATH[:CONFIG] or a recorded folder, one "
                                                  "per robot in id order; one bag with /robotN namespaces (or "
                                                  "one folder) is the whole team.")],
        mode: Annotated[str, typer.Option(help="distributed, centralized or odometry.")] = "distributed",
        out: Annotated[Path, typer.Option(help="Run folder, as `sim` writes it.")] = Path("runs/replay"),
        truth: Truth = None,
        bag_config: BagConfig = None,
        out_bag: Annotated[Path | None, typer.Option("--out-bag", help="Also write each robot's trajectory, "
                                                     "team map and objects into this ROS 2 bag.")] = None,
        config: ConfigFile = None,
        verbose: Annotated[bool, typer.Option("--verbose", "-v")] = False,
    ) -> None:
        """Run the team on recorded data, as `sim` runs it, and score it when ground truth is known."""
        from kimera_multi_py.team.config import load_config
        from kimera_multi_py.workflow.replay import replay as run_replay

        setup_logging(verbose)
        try:
            settings = load_config(config, {})
            results = run_replay(source, mode=mode, out_dir=out, truth=truth or (), bag_config=bag_config,
                                 config=settings, out_bag=out_bag)
        except KimeraMultiError as exc:
            raise fail(exc) from None
        res = results.to_dict()
        console.print(results_table(res))
        summary(res)
        console.print(f"replay of {res['team']['keyframes']} keyframes in {res['wall_s']:.1f} s; "
                      f"wrote {out / 'results.json'}" + (f" and {out_bag}" if out_bag else ""))
