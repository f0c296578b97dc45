"""The ``kimera-multi config`` command: every parameter, its default and what it does (docs/architecture.md)."""

from __future__ import annotations

from typing import Annotated

import typer

from kimera_multi_py.cli.common import ConfigFile, console, fail
from kimera_multi_py.core.errors import KimeraMultiError


def register(app: typer.Typer) -> None:
    """Add the ``config`` command to ``app``."""

    @app.command("config")
    def config_command(
        dump: Annotated[bool, typer.Option("--dump", help="Print the configuration as YAML, a comment per "
                                                          "field: the defaults, or FILE resolved with --config.")]
        = False,
        config: ConfigFile = None,
    ) -> None:
        """Print the default configuration (--dump), or check a configuration file (--config FILE)."""
        from kimera_multi_py.team.config import KimeraConfig, load_config

        if not dump and config is None:
            raise typer.BadParameter("give --dump (print the defaults) or --config FILE (check a file)")
        try:
            settings = load_config(config) if config is not None else KimeraConfig.defaults()
        except KimeraMultiError as exc:
            raise fail(exc) from None
        if dump:
            typer.echo(settings.to_yaml(), nl=False)
        else:
            console.print(f"{config}: valid")
