"""Configuration loading: TOML and YAML files, environment overrides and pydantic validation.

Each component keeps its own parameters next to the code that uses it (the simulator's
scenario lives in :mod:`kimera_multi_py.sim.scenario`). This module turns any source of
trouble -- a missing file, bad TOML or YAML, a wrong type, an out-of-range value -- into a single
:class:`~kimera_multi_py.core.errors.ConfigError` that names the offending field.

Scenario files take environment overrides as ``KMP_`` plus the field path joined by ``__``;
values are parsed as TOML scalars or arrays, e.g. ``KMP_SENSOR__ROWS=32`` or
``KMP_GROUND_TRUTH__RESOLUTION=0.2``. The run configuration
(:class:`~kimera_multi_py.team.config.KimeraConfig`, docs/architecture.md) uses the same prefix
through pydantic-settings (``KMP_AGENT__BUDGET=40``); each reads only its own top-level names.

:func:`param_group` derives a configuration section from a parameter dataclass: the same
fields, types and defaults (one source of truth), the fields' docstrings as descriptions, and
:meth:`ParamGroup.build` to make the dataclass the code runs with. :func:`commented_yaml` writes a
model as YAML with each field's description as a comment.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import os
import textwrap
import tomllib
import typing
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any, ClassVar, Generic, Self, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, model_validator

from kimera_multi_py.core.errors import ConfigError

ENV_PREFIX = "KMP_"
M = TypeVar("M", bound=BaseModel)
T = TypeVar("T")


class StrictModel(BaseModel):
    """Base for config models: unknown keys are errors; a field's docstring is its description."""

    model_config = ConfigDict(extra="forbid", strict=False, frozen=False, use_attribute_docstrings=True,
                              ser_json_inf_nan="constants")


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


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Parse a YAML file holding a mapping; a missing file or a syntax error becomes a ConfigError."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(str(path), "file not found") from None
    except yaml.YAMLError as exc:
        raise ConfigError(str(path), f"invalid YAML: {' '.join(str(exc).split())}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(str(path), f"invalid YAML: not UTF-8 text (byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(str(path), f"cannot read: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(str(path), f"expected a mapping of sections, got {type(data).__name__}")
    return data


def load_file(path: str | Path) -> dict[str, Any]:
    """A ``.toml`` file as TOML, anything else (``.yaml``, ``.yml``) as YAML."""
    return load_toml(path) if Path(path).suffix.lower() == ".toml" else load_yaml(path)


def _parse_env_value(raw: str) -> Any:
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        return raw  # a bare string


def apply_env_overrides(
    data: dict[str, Any], prefix: str = ENV_PREFIX, environ: Mapping[str, str] | None = None,
    names: Collection[str] | None = None,
) -> dict[str, Any]:
    """Return a copy of ``data`` with ``PREFIX`` + ``A__B`` environment variables set at ``a.b``;
    with ``names``, only variables whose first part is one of them (a model's top-level fields)."""
    environ = os.environ if environ is None else environ
    out: dict[str, Any] = {k: v for k, v in data.items()}
    for name, raw in sorted(environ.items()):
        if not name.startswith(prefix) or len(name) == len(prefix):
            continue
        path = [p.lower() for p in name[len(prefix) :].split("__")]
        if names is not None and path[0] not in names:
            continue
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


def config_error(exc: ValidationError, source: str = "") -> ConfigError:
    """The first error of a validation as a ConfigError naming the field (and how many more there are)."""
    err = exc.errors()[0]
    field = format_loc(tuple(err["loc"]))
    msg = err["msg"].removeprefix("Value error, ")
    if "input" in err and err["type"] not in ("missing", "value_error"):
        msg = f"{msg} (got {err['input']!r})"
    more = len(exc.errors()) - 1
    if more:
        msg += f" (+{more} more error{'s' if more > 1 else ''})"
    prefix = f"{source}: " if source else ""
    return ConfigError(f"{prefix}{field}", msg)


def validate(model: type[M], data: Any, source: str = "") -> M:
    """Validate ``data`` against ``model``; the first error becomes a ConfigError naming the field."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise config_error(exc, source) from None


def load_model(model: type[M], path: str | Path, env: bool = True) -> M:
    """Load a TOML file, apply ``KMP_*`` environment overrides and validate against ``model``."""
    data = load_toml(path)
    if env:
        data = apply_env_overrides(data, names=model.model_fields)
    return validate(model, data, source=str(path))


# ---------------------------------------------------------------------------- sections from dataclasses
def attribute_docs(cls: type) -> dict[str, str]:
    """The docstrings of a class's fields (a string right below the field), base classes first."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__[:-1]):
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, after in zip(body, body[1:], strict=False):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                docs[node.target.id] = inspect.cleandoc(after.value.value)
    return docs


class ParamGroup(StrictModel, Generic[T]):
    """A configuration section mirroring a parameter dataclass (made by :func:`param_group`).

    Fields set explicitly (by a file, the environment or the command line) win over what a runner
    chooses for its own kind of run (:meth:`build`); the others keep the runner's choice, else the
    section's default.
    """

    runtime: ClassVar[type]

    def build(self, **runner: Any) -> T:
        """The dataclass the code runs with: this section's values, where not set explicitly
        replaced by ``runner``'s (which also gives the fields the section leaves out)."""
        values = dict(self)
        values.update({k: v for k, v in runner.items() if k not in self.model_fields_set})
        return typing.cast(T, self.runtime(**values))

    @classmethod
    def of(cls, obj: Any) -> Self:
        """The section holding a dataclass's values, every field set (what a run ran with)."""
        return cls.model_validate({name: getattr(obj, name) for name in cls.model_fields})

    @model_validator(mode="after")
    def _dataclass_checks(self) -> Self:
        """The dataclass's own checks (its ``__post_init__``) at load time."""
        try:
            self.runtime(**dict(self))
        except ConfigError as exc:  # named by its own path: keep the field's name
            raise ValueError(f"{exc.field.rpartition('.')[2]}: {exc.problem}" if exc.field else exc.problem) from None
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        return self


def param_group(cls: type[T], name: str, *, defaults: T | None = None, exclude: Collection[str] = (),
                types: Mapping[str, Any] | None = None) -> type[ParamGroup[T]]:
    """A :class:`ParamGroup` model with the fields of dataclass ``cls``: their types (``types``
    replaces some), defaults (read from the instance ``defaults`` if given, e.g. a runner's
    preset) and docstrings (as descriptions), less those named in ``exclude``."""
    hints = typing.get_type_hints(cls)
    docs = attribute_docs(cls)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        if f.name in exclude or not f.init:
            continue
        if defaults is not None:
            info = Field(default=getattr(defaults, f.name), description=docs.get(f.name))
        elif f.default is not dataclasses.MISSING:
            info = Field(default=f.default, description=docs.get(f.name))
        elif f.default_factory is not dataclasses.MISSING:
            info = Field(default_factory=f.default_factory, description=docs.get(f.name))
        else:
            info = Field(description=docs.get(f.name))
        fields[f.name] = ((types or {}).get(f.name, hints[f.name]), info)
    model = create_model(name, __base__=ParamGroup, __doc__=cls.__doc__, **fields)
    model.runtime = cls
    return model


# ---------------------------------------------------------------------------- YAML with comments
def _flow_yaml(value: Any) -> str:
    """One value as one line of flow-style YAML."""
    text = yaml.safe_dump(value, default_flow_style=True, sort_keys=False, width=1 << 20, allow_unicode=True)
    return text.removesuffix("\n").removesuffix("\n...").strip()


def commented_yaml(model: BaseModel, indent: int = 0, only_set: bool = False, _off: bool = False) -> str:
    """``model`` as YAML, each field preceded by its description as a comment (nested models nest).

    With ``only_set``, fields not set explicitly (``model_fields_set``) are written commented out,
    so that loading the text sets only what was set. Floats are written exactly (``repr``), so
    loading the text gives back the same values."""
    pad = "  " * indent
    data = model.model_dump(mode="json")
    lines: list[str] = []
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        off = _off or (only_set and name not in model.model_fields_set)
        mark = "# " if off else ""
        if isinstance(value, BaseModel) and lines:
            lines.append("")
        lines += [f"{pad}# {line}".rstrip() for line in (info.description or "").splitlines()]
        if isinstance(value, BaseModel):
            lines.append(f"{pad}{mark}{name}:")
            lines.append(commented_yaml(value, indent + 1, only_set, off).rstrip("\n"))
        else:
            lines.append(f"{pad}{mark}{name}: {_flow_yaml(data[name])}")
    return "\n".join(lines) + "\n"
