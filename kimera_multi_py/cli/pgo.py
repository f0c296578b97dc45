"""The ``kimera-multi pgo`` command. The lead's ``cli.py`` calls :func:`register`."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from kimera_multi_py.core.errors import KimeraMultiError

# the distributed solver of ``kimera-multi pgo`` (and of benchmarks/pgo.py): distributed
# Levenberg–Marquardt (pgo.gn) reaches a 1e-3 gap within the 500-round cap on every
# graph of shared/datasets/pgo, where block SOR stalls on parking-garage and cubicle; robust
# runs put GNC on its outer loop (pgo.gn_weights). The team PGO inside the agents
# keeps block SOR (PgoParams' default), and so does run_pgo called without a method
# (workflow.DEFAULT_METHOD).
CLI_METHOD = "gn_pcg"


def register(app: typer.Typer) -> None:
    """Add the ``pgo`` command to ``app``."""

    @app.command("pgo")
    def pgo(
        inputs: Annotated[list[Path], typer.Argument(
            help="a g2o or TORO file, 3-D or 2-D (split among robots), several multi-robot g2o "
                 "files, or a DPGO robotK/measurements.csv folder")],
        robots: Annotated[int, typer.Option(help="robots for a single-robot g2o")] = 5,
        transport: Annotated[str, typer.Option(help="loopback | zenoh")] = "loopback",
        robust: Annotated[bool, typer.Option("--robust", help=(
            "GNC-TLS on closures; scored by TLS cost, inlier sets and their Jaccard (precision "
            "and recall only with --outliers)"))] = False,
        outliers: Annotated[float, typer.Option(
            help="add this fraction of wrong inter-robot closures")] = 0.0,
        seed: Annotated[int, typer.Option(help="seed of outliers and message faults")] = 0,
        max_rounds: Annotated[int, typer.Option(help="round cap")] = 500,
        method: Annotated[str | None, typer.Option(help=(
            "gn_pcg (distributed Levenberg-Marquardt with two-level CG, the default) | "
            "block_sor (block Gauss-Seidel with adaptive over-relaxation)"))] = None,
        json_out: Annotated[Path | None, typer.Option("--json", help="write figures here")] = None,
        out: Annotated[Path | None, typer.Option(help="write g2o, TUM and results.json here")]
        = None,
    ) -> None:
        """Distributed PGO against the centralised reference on the same graph."""
        from rich.console import Console
        from rich.table import Table

        from kimera_multi_py.workflow.pgo_benchmark import run_pgo

        console = Console()
        try:
            result = run_pgo(inputs, robots=robots, transport=transport, robust=robust,
                             outliers=outliers, seed=seed, max_rounds=max_rounds, out_dir=out,
                             method=method or CLI_METHOD)
        except KimeraMultiError as exc:
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(1) from None
        figures = result.to_json()
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(figures, indent=2))
        table = Table(title=f"PGO {figures['dataset']} ({figures['robots']} robots)")
        table.add_column("figure")
        table.add_column("value", justify="right")
        for key, value in figures.items():
            if isinstance(value, dict):
                continue
            table.add_row(key, f"{value:.6g}" if isinstance(value, float) else str(value))
        console.print(table)
        if not result.reference_converged:
            console.print(result.reference)
