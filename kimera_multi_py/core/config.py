"""Configuration loading: TOML files, environment overrides and pydantic validation.

Each component keeps its own pydantic model next to the code that uses it (the simulator's
scenario lives in :mod:`kimera_multi_py.sim.scenario`). This module turns any source of
trouble -- a missing file, bad TOML, a wrong type, an out-of-range value -- into a single
:class:`~kimera_multi_py.core.errors.ConfigError` that names the offending field.

Environment overrides use ``KMP_`` plus the field path joined by ``__``; values are parsed as
TOML scalars or arrays, e.g. ``KMP_SENSOR__ROWS=32`` or ``KMP_GROUND_TRUTH__RESOLUTION=0.2``.
"""

from __future__ import annotations

import os
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from kimera_multi_py.core.errors import ConfigError

ENV_PREFIX = "KMP_"
M = TypeVar("M", bound=BaseModel)


class StrictModel(BaseModel):
    """Base for config models: unknown keys are errors, values are not coerced across types."""

    model_config = ConfigDict(extra="forbid", strict=False, frozen=False)


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a missing file or a syntax error becomes a ConfigError."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(str(path), "file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), f"invalid TOML: {exc}") from None
    except UnicodeDecodeError as exc:  # tomllib decodes UTF-8 itself
        raise ConfigError(str(path), f"invalid TOML: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read: {exc}") from None


def _parse_env_value(raw: str) -> Any:
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw  # a bare string


def apply_env_overrides(
    data: dict[str, Any], prefix: str = ENV_PREFIX, environ: Mapping[str, str] | None = None
) -> dict[str, Any]:
    """Return a copy of ``data`` with ``PREFIX`` + ``A__B`` environment variables set at ``a.b``."""
    environ = os.environ if environ is None else environ
    out: dict[str, Any] = {k: v for k, v in data.items()}
    for name, raw in sorted(environ.items()):
        if not name.startswith(prefix) or len(name) == len(prefix):
            continue
        path = [p.lower() for p in name[len(prefix) :].split("__")]
        node = out
        for part in path[:-1]:
            child = node.get(part)
            child = dict(child) if isinstance(child, dict) else {}
            node[part] = child
            node = child
        node[path[-1]] = _parse_env_value(raw)
    return out


def format_loc(loc: tuple[int | str, ...]) -> str:
    """``("robots", 1, "speed")`` -> ``robots[1].speed``."""
    text = ""
    for part in loc:
        if isinstance(part, int):
            text += f"[{part}]"
        else:
            text += ("." if text else "") + str(part)
    return text or "<root>"


def validate(model: type[M], data: Any, source: str = "") -> M:
    """Validate ``data`` against ``model``; the first error becomes a ConfigError naming the field."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        field = format_loc(tuple(err["loc"]))
        msg = err["msg"]
        if "input" in err and err["type"] not in ("missing",):
            msg = f"{msg} (got {err['input']!r})"
        more = len(exc.errors()) - 1
        if more:
            msg += f" (+{more} more error{'s' if more > 1 else ''})"
        prefix = f"{source}: " if source else ""
        raise ConfigError(f"{prefix}{field}", msg) from None


def load_model(model: type[M], path: str | Path, env: bool = True) -> M:
    """Load a TOML file, apply ``KMP_*`` environment overrides and validate against ``model``."""
    data = load_toml(path)
    if env:
        data = apply_env_overrides(data)
    return validate(model, data, source=str(path))
