"""The map-sharing protocol (docs/algorithms/mapping.md): octree deltas, the exact map consensus
(submap evidence, submap poses, version summaries), the laplacian and roam baselines, and the
team's object landmarks and people tracks.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms import keys
from kimera_multi_py.comms.messages.base import Message, message
from kimera_multi_py.comms.messages.fields import (
    INT64_MAX,
    MAX_ROBOT_ID,
    Array,
    Bool,
    Float,
    Int,
    arr,
    count,
    robot_id,
    spec_field,
)


@message("MapDelta", keys.MAP_DELTA)
class MapDelta(Message):
    """Changed octree cells: Morton keys and int8-quantised log-odds (``h = logodds * scale``).

    Cells are in the world frame of robot ``frame`` at ``depth`` / ``resolution``; ``full`` marks a
    complete snapshot rather than a delta. ``logodds`` has K+1 columns (column 0 = free).
    """

    robot: int = robot_id()
    round: int = count()
    frame: int = robot_id()
    resolution: float = spec_field(Float(lo=1e-9))
    depth: int = spec_field(Int(0, 21))
    full: bool = spec_field(Bool())
    keys: np.ndarray = arr("int64", "n", lo=0)
    logodds: np.ndarray = arr("int8", "n", "c")
    scale: float = spec_field(Float(lo=1e-12))


@message("SubmapEvidence", keys.MAP_EVIDENCE)
class SubmapEvidence(Message):
    """Map consensus (exact): the cells of ``source``'s submap ``submap`` that changed after
    version ``base``, as they are at ``version`` (absolute values, so re-applying is harmless).

    ``payload`` holds ``cells`` Morton codes on the submap's reference grid and their integer
    evidence (fixed-point log-odds sums) of ``classes`` classes 1..K, losslessly compressed
    (:mod:`kimera_multi_py.mapshare.wire`). A robot at a version in ``[base, version)``
    applies it; relayed unchanged except for ``robot`` (the sender) and ``seq``. ``seq`` numbers
    the sender's evidence messages (1, 2, ...; the receivers' summaries acknowledge it).
    """

    robot: int = robot_id()
    source: int = robot_id()
    submap: int = count()
    base: int = count()
    version: int = count()
    cells: int = count()
    classes: int = spec_field(Int(1, 255))
    payload: np.ndarray = arr("uint8", "b")
    seq: int = spec_field(Int(0, INT64_MAX), default=0)


@message("SubmapPoses", keys.MAP_POSES)
class SubmapPoses(Message):
    """Map consensus: where ``source``'s submaps are (version ``version`` of its pose table).

    ``frame`` is the root robot of the world frame the poses ``T`` are in; ``T_ref`` are the
    poses at which each submap's grid was laid down. Relayed unchanged except for ``robot`` and
    ``seq`` (the sender's pose-table messages numbered 1, 2, ...).
    """

    robot: int = robot_id()
    source: int = robot_id()
    version: int = count()
    frame: int = robot_id()
    submaps: np.ndarray = arr("int64", "n", lo=0)
    T_ref: np.ndarray = arr("float64", "n", 4, 4)
    T: np.ndarray = arr("float64", "n", 4, 4)
    seq: int = spec_field(Int(0, INT64_MAX), default=0)


@message("MapVersions", keys.MAP_VERSIONS)
class MapVersions(Message):
    """Map consensus: the versions of every submap and pose table a robot holds (a summary its
    neighbours answer with what it lacks, which also recovers lost messages).

    ``ack_robots[i]``'s evidence and pose-table messages received so far: the highest ``seq`` of
    each (``ack_evidence[i]``, ``ack_poses[i]``; docs/algorithms/map_consensus.md, "Losses")."""

    robot: int = robot_id()
    frame: int = robot_id()
    sources: np.ndarray = arr("int32", "m", lo=0, hi=MAX_ROBOT_ID)
    submaps: np.ndarray = arr("int64", "m", lo=0)
    versions: np.ndarray = arr("int64", "m", lo=0)
    pose_sources: np.ndarray = arr("int32", "p", lo=0, hi=MAX_ROBOT_ID)
    pose_versions: np.ndarray = arr("int64", "p", lo=0)
    ack_robots: np.ndarray = spec_field(Array("int32", ("a",), lo=0, hi=MAX_ROBOT_ID),
                                        factory=lambda: np.zeros(0, np.int32))
    ack_evidence: np.ndarray = spec_field(Array("int64", ("a",), lo=0), factory=lambda: np.zeros(0, np.int64))
    ack_poses: np.ndarray = spec_field(Array("int64", ("a",), lo=0), factory=lambda: np.zeros(0, np.int64))


@message("MapState", keys.MAP_STATE)
class MapState(Message):
    """Map consensus (laplacian): a robot's consensus state at ``round`` in frame ``frame``.

    ``values[:, 0]`` is the averaged support count, ``values[:, 1:]`` the averaged evidence of
    classes 1..K; ``full`` marks a refresh of every cell, otherwise only the cells changed since
    the last round travel. A round's cells may span several messages of the same ``round``.
    ``degree`` is the sender's neighbour count (Metropolis-Hastings weights).
    """

    robot: int = robot_id()
    round: int = count()
    frame: int = robot_id()
    degree: int = count()
    full: bool = spec_field(Bool())
    codes: np.ndarray = arr("int64", "n", lo=0)
    values: np.ndarray = arr("float64", "n", "c")


@message("RoamMap", keys.MAP_ROAM)
class RoamMap(Message):
    """Map consensus (roam baseline): a robot's full pruned tree, as ROAM's code sends it.

    ``payload`` holds ``leaves`` leaves in Morton order (start codes, levels, fixed-point rows of
    ``classes`` classes 1..K), losslessly compressed so that a large tree fits in one message;
    ``nodes`` is the tree's node count with inner nodes, for which ROAM's own (uncompressed)
    wire format pays 36 B each.
    """

    robot: int = robot_id()
    round: int = count()
    frame: int = robot_id()
    nodes: int = count()
    leaves: int = count()
    classes: int = spec_field(Int(1, 255))
    payload: np.ndarray = arr("uint8", "b")


@message("ObjectUpdate", keys.OBJECTS)
class ObjectUpdate(Message):
    """Object sharing: version ``version`` of ``source``'s table of confirmed object landmarks.

    Each object is anchored in one of the source's submaps (``submaps``) and its geometry is in
    that submap's reference frame (``T_ref`` of the source's :class:`SubmapPoses`), so a PGO
    correction moves it with the submap and the table itself need not travel again. Per object:
    id (the source's landmark id), MAP class, class posterior ``probs`` (n, C), box centre
    ``centroids`` and axis-aligned half extents ``extents`` (reference frame), and sightings.
    ``frame`` is the sender's frame when sent. Relayed unchanged except for ``robot`` and
    ``held_sources`` / ``held_versions``: the newest version of each source's table the sender
    holds (so its neighbours need not send it what it has).

    ``base`` > 0 makes the message a row delta (:mod:`kimera_multi_py.mapshare.table_delta`):
    the table is version ``base`` of the same source with ``reuse`` (one entry per row: a base
    row's index, or -1) and the row fields hold only the rows marked -1. ``base`` 0 is the table
    itself, with ``reuse`` empty.
    """

    robot: int = robot_id()
    source: int = robot_id()
    version: int = count()
    frame: int = robot_id()
    ids: np.ndarray = arr("int64", "n", lo=0)
    submaps: np.ndarray = arr("int64", "n", lo=0)
    classes: np.ndarray = arr("int32", "n", lo=0)
    probs: np.ndarray = arr("float32", "n", "c", lo=0.0, hi=1.0)
    centroids: np.ndarray = arr("float64", "n", 3)
    extents: np.ndarray = arr("float64", "n", 3, lo=0.0)
    sightings: np.ndarray = arr("int32", "n", lo=0)
    held_sources: np.ndarray = spec_field(Array("int32", ("h",), lo=0, hi=MAX_ROBOT_ID),
                                          factory=lambda: np.zeros(0, np.int32))
    held_versions: np.ndarray = spec_field(Array("int64", ("h",), lo=0), factory=lambda: np.zeros(0, np.int64))
    base: int = spec_field(Int(0, INT64_MAX), default=0)
    reuse: np.ndarray = spec_field(Array("int32", ("r",), lo=-1), factory=lambda: np.zeros(0, np.int32))


@message("PeopleUpdate", keys.PEOPLE)
class PeopleUpdate(Message):
    """People sharing: version ``version`` of ``source``'s confirmed people tracks, one row per
    sample: the track's id (the source's), the sample's stamp, the submap it was seen from and its
    position in that submap's reference frame (``T_ref`` of the source's :class:`SubmapPoses`), so
    a PGO correction moves it as it moves objects. ``frame`` is the sender's frame when sent.
    Relayed unchanged except for ``robot``. ``held_sources``, ``held_versions``, ``base`` and
    ``reuse`` as in :class:`ObjectUpdate`.
    """

    robot: int = robot_id()
    source: int = robot_id()
    version: int = count()
    frame: int = robot_id()
    tracks: np.ndarray = arr("int64", "n", lo=0)
    stamps: np.ndarray = arr("float64", "n", lo=0.0)
    submaps: np.ndarray = arr("int64", "n", lo=0)
    positions: np.ndarray = arr("float64", "n", 3)
    held_sources: np.ndarray = spec_field(Array("int32", ("h",), lo=0, hi=MAX_ROBOT_ID),
                                          factory=lambda: np.zeros(0, np.int32))
    held_versions: np.ndarray = spec_field(Array("int64", ("h",), lo=0), factory=lambda: np.zeros(0, np.int64))
    base: int = spec_field(Int(0, INT64_MAX), default=0)
    reuse: np.ndarray = spec_field(Array("int32", ("r",), lo=-1), factory=lambda: np.zeros(0, np.int32))
