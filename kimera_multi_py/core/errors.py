"""Exception hierarchy. Library code raises these; only the CLI turns them into exit codes."""

from __future__ import annotations


class KimeraMultiError(Exception):
    """Base of every error this package raises on purpose."""


class ConfigError(KimeraMultiError):
    """A scenario or component configuration is invalid. The message names the field."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}" if field else problem)


class MessageError(KimeraMultiError):
    """A message on the wire is malformed. The message names the field."""


class DatasetError(KimeraMultiError):
    """A dataset file is malformed or inconsistent. The message names file and line."""


class GraphError(KimeraMultiError):
    """A factor graph is inconsistent (unknown key, disconnected, NaN values, ...)."""


class MapError(KimeraMultiError):
    """A map file is corrupt, truncated or of an unknown format version."""


class CheckpointError(KimeraMultiError):
    """A checkpoint file is missing, corrupt, truncated, foreign or of another format version.

    The message names the file and the problem.
    """

    def __init__(self, path: str, problem: str) -> None:
        self.path = path
        self.problem = problem
        super().__init__(f"{path}: {problem}")
