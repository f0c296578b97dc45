"""Every key expression the team uses, and a small matcher for them.

Layout (docs/architecture.md):

- topics: ``kmp/{team}/r{robot}/{topic}``, e.g. ``kmp/t0/r2/pgo/public_poses``;
- presence: a liveliness token at ``kmp/{team}/alive/r{robot}``;
- large data on request: a queryable at ``kmp/{team}/r{robot}/keyframe/{id}``.

Wildcards follow Zenoh: ``*`` matches exactly one chunk, ``**`` matches zero or more chunks.
:func:`intersects` implements that subset so the in-process bus needs no Zenoh.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache

from kimera_multi_py.core.errors import MessageError

ROOT = "kmp"

# Topics (the part after ``kmp/{team}/r{robot}/``).
PUBLIC_POSES = "pgo/public_poses"
POSE_DELTAS = "pgo/pose_deltas"
PGO_STATUS = "pgo/status"
PGO_COMMAND = "pgo/command"
GNC_WEIGHTS = "pgo/gnc_weights"
EDGE_VETO = "pgo/edge_veto"
PCG_STATE = "pgo/pcg_state"
FRAME_LANDMARKS = "pgo/landmarks"
DESCRIPTORS = "lc/descriptors"
LC_REQUEST = "lc/request"
LC_REPLY = "lc/reply"
LOOP_CLOSURES = "lc/closures"
LOOP_CLOSURES_ACK = "lc/ack"
MAP_DELTA = "map/delta"
MAP_EVIDENCE = "map/evidence"
MAP_POSES = "map/poses"
MAP_VERSIONS = "map/versions"
MAP_STATE = "map/state"
MAP_ROAM = "map/roam"
OBJECTS = "map/objects"
PEOPLE = "map/people"
HEARTBEAT = "heartbeat"
PING = "diag/ping"
KEYFRAME = "keyframe"
ODOMETRY = "server/odometry"
PGO_EPOCH = "pgo/epoch"
AGENT_STATE = "state"

_TEAM_RE = re.compile(r"^[A-Za-z0-9_\-]{1,32}$")
_ROBOT_RE = re.compile(r"^r(0|[1-9][0-9]{0,5})$")
_TOPIC_CHUNK_RE = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")


def check_team(team: str) -> str:
    """Return ``team`` if it is a valid team id (1-32 of ``[A-Za-z0-9_-]``), else raise."""
    if not isinstance(team, str) or not _TEAM_RE.match(team):
        raise MessageError(f"team: invalid team id {team!r}")
    return team


def robot_chunk(robot: int) -> str:
    """The key chunk naming robot ``robot``: ``r{robot}``."""
    if isinstance(robot, bool) or not isinstance(robot, int) or robot < 0:
        raise MessageError(f"robot: invalid robot id {robot!r}")
    return f"r{robot}"


def _check_topic(topic: str) -> str:
    chunks = topic.split("/")
    if not topic or not all(_TOPIC_CHUNK_RE.match(c) for c in chunks):
        raise MessageError(f"topic: invalid topic {topic!r}")
    return topic


def topic_key(team: str, robot: int, topic: str) -> str:
    """The concrete key on which robot ``robot`` publishes ``topic``."""
    return f"{ROOT}/{check_team(team)}/{robot_chunk(robot)}/{_check_topic(topic)}"


def topic_all(team: str, topic: str) -> str:
    """A key expression matching ``topic`` from every robot of ``team``."""
    return f"{ROOT}/{check_team(team)}/*/{_check_topic(topic)}"


def robot_all(team: str, robot: int) -> str:
    """A key expression matching every topic of one robot."""
    return f"{ROOT}/{check_team(team)}/{robot_chunk(robot)}/**"


def team_all(team: str) -> str:
    """A key expression matching every topic of every robot of ``team`` (not presence)."""
    return f"{ROOT}/{check_team(team)}/*/**"


def alive_key(team: str, robot: int) -> str:
    """The liveliness token key of robot ``robot``."""
    return f"{ROOT}/{check_team(team)}/alive/{robot_chunk(robot)}"


def alive_all(team: str) -> str:
    """A key expression matching every presence token of ``team``."""
    return f"{ROOT}/{check_team(team)}/alive/*"


def keyframe_key(team: str, robot: int, keyframe: int | str) -> str:
    """The queryable key serving keyframe ``keyframe`` of ``robot`` (``*`` for all of them)."""
    if keyframe != "*" and (isinstance(keyframe, bool) or not isinstance(keyframe, int)):
        raise MessageError(f"keyframe: invalid keyframe id {keyframe!r}")
    return f"{topic_key(team, robot, KEYFRAME)}/{keyframe}"


@dataclass(frozen=True)
class ParsedKey:
    """A concrete key split into its parts. ``robot`` is None for presence keys."""

    team: str
    robot: int | None
    topic: str
    alive: bool = False


def parse_key(key: str) -> ParsedKey:
    """Split a concrete key into team, robot and topic; raise :class:`MessageError` if foreign."""
    chunks = key.split("/")
    if len(chunks) < 4 or chunks[0] != ROOT:
        raise MessageError(f"key: not a {ROOT} key: {key!r}")
    team = check_team(chunks[1])
    if chunks[2] == "alive":
        if len(chunks) != 4 or not _ROBOT_RE.match(chunks[3]):
            raise MessageError(f"key: invalid presence key {key!r}")
        return ParsedKey(team, int(chunks[3][1:]), "alive", alive=True)
    if not _ROBOT_RE.match(chunks[2]):
        raise MessageError(f"key: invalid robot chunk in {key!r}")
    return ParsedKey(team, int(chunks[2][1:]), "/".join(chunks[3:]))


@lru_cache(maxsize=4096)
def topic_label(key: str) -> str:
    """The counter label of a key: its topic with numeric chunks (ids) removed.

    ``kmp/t0/r1/keyframe/17`` -> ``keyframe``; a key that does not parse keeps its own name.
    """
    try:
        topic = parse_key(key).topic
    except MessageError:
        return key
    return "/".join(c for c in topic.split("/") if not c.isdigit()) or topic


@lru_cache(maxsize=4096)
def intersects(a: str, b: str) -> bool:
    """True when key expressions ``a`` and ``b`` share at least one concrete key.

    Supports Zenoh's ``*`` (one chunk) and ``**`` (any number of chunks, including none).
    """
    return _match(tuple(a.split("/")), tuple(b.split("/")))


def _match(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a:
        return all(c == "**" for c in b)
    if not b:
        return all(c == "**" for c in a)
    if a[0] == "**":
        return _match(a[1:], b) or _match(a, b[1:])
    if b[0] == "**":
        return _match(a, b[1:]) or _match(a[1:], b)
    if a[0] == "*" or b[0] == "*" or a[0] == b[0]:
        return _match(a[1:], b[1:])
    return False


def is_concrete(key: str) -> bool:
    """True when ``key`` has no wildcard chunk."""
    return "*" not in key and "$" not in key and bool(key)
