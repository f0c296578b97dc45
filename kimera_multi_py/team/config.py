"""One configuration for every run: :class:`KimeraConfig` (docs/architecture.md).

A run's parameters live in one typed model built on pydantic-settings. Its sections mirror the
parameter dataclasses the code runs with, and take their fields, types, defaults and
descriptions from them (:func:`~kimera_multi_py.core.config.param_group`), so every default has
one home, next to the code that uses it:

=================  ==========================================================================
``run``            what the commands choose: scenario, seed, team size, mode, transport, ...
``agent``          :class:`~kimera_multi_py.agent.params.AgentParams` (less ``mapping``, ``server``)
``pgo``            :class:`~kimera_multi_py.pgo.params.PgoParams`, defaults of ``team_params()``
``node``           :class:`~kimera_multi_py.agent.node.NodeParams` (less ``server``)
``schedule``       :class:`~kimera_multi_py.pgo.team.ScheduleParams`
``map_consensus``  :class:`~kimera_multi_py.mapshare.consensus.MapConsensusParams` (mode: ``node``'s)
``scene_graph``    :class:`~kimera_multi_py.scene_graph.params.SceneGraphParams`
``mapping``        :class:`~kimera_multi_py.mapping.config.MappingConfig`
=================  ==========================================================================

:func:`load_config` reads, lowest first: the defaults, a YAML or TOML file, ``KMP_*`` environment
variables (``KMP_AGENT__BUDGET=40``, ``KMP_SCHEDULE__ROUND_TIMEOUT=null``; lists as JSON), and the
command line's explicit flags. A runner keeps its own choices (the agent process's
``final_grace``, the simulator's loopback rounds without a wall-clock timeout, the keyframe
source's noise model) for every field not set explicitly. Every run folder gets ``config.yaml``,
the full configuration it ran with (docs/outputs.md): ``--config config.yaml`` runs it again.
"""

from __future__ import annotations

import os
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BeforeValidator, Field, ValidationError
from pydantic_settings import BaseSettings, InitSettingsSource, PydanticBaseSettingsSource, SettingsConfigDict

from kimera_multi_py.agent.node import NodeParams
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms.faults import parse_partition
from kimera_multi_py.comms.loopback import Faults, Partition
from kimera_multi_py.core.config import (
    ENV_PREFIX,
    ParamGroup,
    StrictModel,
    commented_yaml,
    config_error,
    load_file,
    param_group,
)
from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.ids import MAX_AGENT_ID, MAX_ROBOTS
from kimera_multi_py.mapping.config import MappingConfig
from kimera_multi_py.mapshare.consensus import MapConsensusParams
from kimera_multi_py.pgo.params import PgoParams, team_params
from kimera_multi_py.pgo.team import ScheduleParams
from kimera_multi_py.scene_graph.params import SceneGraphParams
from kimera_multi_py.sim.scenario import ScenarioConfig

CONFIG_NAME = "config.yaml"
DEFAULT_SCENARIO = Path("sims/office.toml")


def _partition(value: Any) -> Any:
    """A partition as ``"0,1|2@60:120"`` (the command line's form) or as its fields."""
    try:
        return parse_partition(value) if isinstance(value, str) else value
    except ConfigError as exc:
        raise ValueError(exc.problem) from None


if TYPE_CHECKING:
    AgentSection = ParamGroup[AgentParams]
    PgoSection = ParamGroup[PgoParams]
    NodeSection = ParamGroup[NodeParams]
    ScheduleSection = ParamGroup[ScheduleParams]
    MapConsensusSection = ParamGroup[MapConsensusParams]
    SceneGraphSection = ParamGroup[SceneGraphParams]
    FaultsSection = ParamGroup[Faults]
else:
    AgentSection = param_group(AgentParams, "AgentSection", exclude=("mapping", "server", "people"))
    PgoSection = param_group(PgoParams, "PgoSection", defaults=team_params())
    NodeSection = param_group(NodeParams, "NodeSection", exclude=("server",))
    ScheduleSection = param_group(ScheduleParams, "ScheduleSection")
    MapConsensusSection = param_group(MapConsensusParams, "MapConsensusSection", exclude=("mode",))
    SceneGraphSection = param_group(SceneGraphParams, "SceneGraphSection")
    FaultsSection = param_group(Faults, "FaultsSection", types={
        "partitions": tuple[Annotated[Partition, BeforeValidator(_partition)], ...]})

RobotId = Annotated[int, Field(ge=0, le=MAX_AGENT_ID)]
Seconds = Annotated[float, Field(ge=0, allow_inf_nan=False)]


class RunConfig(StrictModel):
    """What the commands choose for a run. Null: the command's own default (the resolved
    ``config.yaml`` of a run folder holds the values used)."""

    scenario: Path | None = None
    """Scenario file (``sim``, ``launch``); null: sims/office.toml."""
    seed: int | None = None
    """Random seed; null: the scenario's (``launch``: 0)."""
    robots: Annotated[int, Field(ge=1, le=MAX_ROBOTS)] | None = None
    """Team size; null: the scenario's robots (``launch``: 3)."""
    mode: Literal["odometry", "distributed", "centralized"] | None = None
    """odometry (dead reckoning), distributed or centralized; null: ``sim`` odometry, else distributed."""
    transport: Literal["loopback", "zenoh"] | None = None
    """``sim``: loopback (in-process) or zenoh (one session per robot); null: loopback."""
    comm_range: Annotated[float, Field(gt=0)] | None = None
    """``sim``: radio range for map traffic (m); null: unlimited."""
    join: dict[RobotId, Seconds] = {}
    """Robot -> seconds after the others it joins (``launch``: the team's stream time it starts at)."""
    leave: dict[RobotId, Seconds] = {}
    """``sim``: robot -> time at which it leaves for good."""
    faults: FaultsSection = Field(default_factory=FaultsSection)
    """``sim``: loopback link faults (times in s); ``launch`` applies only the partitions (of router links)."""


class _FileSource(InitSettingsSource):
    """A configuration file's contents, below the environment and the command line."""


# what load_config reads besides its overrides: a file's contents, and whether to read the
# environment (elsewhere -- KimeraConfig(...), model_validate -- only the values given count)
_SOURCES: ContextVar[tuple[dict[str, Any], bool] | None] = ContextVar("kimera_config_sources", default=None)


class KimeraConfig(BaseSettings):
    """Every parameter of a run (see the module docstring)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_nested_delimiter="__", env_parse_none_str="null",
                                      extra="forbid", validate_default=False, use_attribute_docstrings=True,
                                      ser_json_inf_nan="constants")

    run: RunConfig = Field(default_factory=RunConfig)
    """What the commands choose for a run."""
    agent: AgentSection = Field(default_factory=AgentSection)
    """The per-robot front end: loop closures, scan registration, PCM."""
    pgo: PgoSection = Field(default_factory=PgoSection)
    """The agents' distributed pose-graph optimisation."""
    node: NodeSection = Field(default_factory=NodeSection)
    """A robot's node on the bus: timeouts, re-sends, the map consensus mode."""
    schedule: ScheduleSection = Field(default_factory=ScheduleSection)
    """When the team optimises (``--pgo-period`` is ``period``)."""
    map_consensus: MapConsensusSection = Field(default_factory=MapConsensusSection)
    """Map consensus knobs (the mode is ``node.map_consensus``)."""
    scene_graph: SceneGraphSection = Field(default_factory=SceneGraphSection)
    """The scene-graph builder (docs/algorithms/scene_graph.md)."""
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    """A robot's maps: semantic octree, objects, submaps."""

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources = _SOURCES.get()
        if sources is None:
            return (init_settings,)
        data, env = sources
        return (init_settings, *((env_settings,) if env else ()), _FileSource(settings_cls, data))

    @classmethod
    def defaults(cls) -> KimeraConfig:
        """The defaults alone (no file, no environment): what the library runs with unless told."""
        return cls.model_validate({})

    # -- the dataclasses the code runs with (``runner``: a runner's own choices, see ParamGroup.build)
    def to_agent_params(self, **runner: Any) -> AgentParams:
        return self.agent.build(mapping=self.mapping, **runner)

    def to_pgo_params(self) -> PgoParams:
        return self.pgo.build()

    def to_node_params(self, **runner: Any) -> NodeParams:
        return self.node.build(**runner)

    def to_schedule(self, **runner: Any) -> ScheduleParams:
        return self.schedule.build(**runner)

    def to_map_params(self) -> MapConsensusParams:
        return self.map_consensus.build()

    def to_scene_graph_params(self) -> SceneGraphParams:
        return self.scene_graph.build()

    def updated(self, overrides: dict[str, Any], source: str = "config") -> KimeraConfig:
        """A copy with ``overrides`` (nested sections as dicts) set explicitly; validated."""
        data = _deep_update(self.model_dump(exclude_unset=True), overrides)
        try:
            return type(self).model_validate(data)
        except ValidationError as exc:
            raise config_error(exc, source) from None

    @classmethod
    def resolved(cls, run: RunConfig | dict[str, Any], agent: AgentParams, pgo: PgoParams, node: NodeParams,
                 schedule: ScheduleParams, map_params: MapConsensusParams,
                 scene_graph: SceneGraphParams) -> KimeraConfig:
        """The configuration of what a run ran with, every field set: loading it back gives the
        same parameters whatever the runner's own choices (docs/outputs.md)."""
        return cls.model_validate({
            "run": run, "agent": AgentSection.of(agent), "pgo": PgoSection.of(pgo), "node": NodeSection.of(node),
            "schedule": ScheduleSection.of(schedule), "map_consensus": MapConsensusSection.of(map_params),
            "scene_graph": SceneGraphSection.of(scene_graph), "mapping": agent.mapping})

    def to_yaml(self, only_set: bool = False) -> str:
        """The configuration as YAML, each field with its description as a comment; with
        ``only_set``, the fields not set explicitly commented out (each process's own choice)."""
        head = ("# kimera-multi-py configuration (docs/architecture.md). Load it with --config FILE;\n"
                "# KMP_SECTION__FIELD environment variables and explicit flags override it.\n")
        if only_set:
            head += ("# Lines '# name: value' are not set: each process keeps its own choice there (the\n"
                     "# defaults shown); the processes' config.yaml hold the values they ran with.\n")
        return head + "\n" + commented_yaml(self, only_set=only_set)

    def write(self, folder: str | Path, only_set: bool = False) -> Path:
        """``FOLDER/config.yaml`` (see :meth:`to_yaml`)."""
        path = Path(folder) / CONFIG_NAME
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.to_yaml(only_set), encoding="utf-8")
        return path


def _deep_update(base: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in new.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_update(out[key], value)
        else:
            out[key] = value
    return out


def _check_env_sections() -> None:
    """A ``KMP_SECTION__FIELD`` variable must name a section of the configuration or of a scenario
    (which reads the same prefix): pydantic-settings would silently ignore a mistyped section."""
    known = set(KimeraConfig.model_fields) | set(ScenarioConfig.model_fields)
    for name in sorted(os.environ):
        head, nested, _ = name[len(ENV_PREFIX):].partition("__")
        if name.startswith(ENV_PREFIX) and nested and head.lower() not in known:
            raise ConfigError(name, f"no section {head.lower()!r} in the configuration or the scenario")


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None,
                env: bool = True) -> KimeraConfig:
    """The configuration from, lowest first: the defaults, the file at ``path`` (YAML, or TOML by
    its ``.toml`` suffix), ``KMP_*`` environment variables (unless ``env`` is false) and
    ``overrides`` (a command line's explicit flags, as nested dicts). Any problem raises
    :class:`~kimera_multi_py.core.errors.ConfigError` naming the field."""
    data = load_file(path) if path is not None else {}
    source = str(path) if path is not None else "config"
    if env:
        _check_env_sections()
    token = _SOURCES.set((data, env))
    try:
        return KimeraConfig(**(overrides or {}))
    except ValidationError as exc:
        raise config_error(exc, source) from None
    finally:
        _SOURCES.reset(token)
