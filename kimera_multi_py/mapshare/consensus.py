"""Map consensus: one robot's pure step towards a team map (docs/algorithms/map_consensus.md).

A :class:`MapConsensus` reads the robot's own :class:`~kimera_multi_py.mapping.submaps.SubmapMap`
(never changes it), absorbs its neighbours' messages with :meth:`MapConsensus.handle` and returns
what to publish from :meth:`MapConsensus.step`; it touches no network, clock or file. Its result
is :attr:`MapConsensus.team_map`, the robot's belief about the whole team's space. Three modes:

``exact`` (ours)
    Robots share their own *evidence*: per submap, the integer sums of ``l(z)`` on the submap's
    reference grid. A :class:`SubmapEvidence` carries the cells of ``(source, submap)`` changed
    after version ``base`` with their values at ``version`` (absolute values): a robot at a
    version in ``[base, version)`` applies it, any other ignores it, so duplicates and reordering
    are harmless and nothing is ever counted twice. The robot's newest submap, still growing,
    gets a version at most every ``hold`` seconds (each version would otherwise re-send most of
    its cells every period); an older one gets its last version at once. A :class:`SubmapPoses` carries a source's
    pose table (versioned, with the frame it is in): after a PGO correction only it travels and
    the submaps move exactly. Every robot relays what a neighbour lacks, so evidence crosses the
    team one hop at a time. A :class:`MapVersions` summary (sent when it changes and every
    ``summary_every`` periods) tells the neighbours what the robot holds and acknowledges what
    it received (:mod:`.acks`); a neighbour re-sends what a summary made after its send arrived
    still lacks, which recovers lost messages and partitions. The team map is
    ``clamp(prior + sum T_s dh_s)`` over every held submap whose source is in the robot's frame
    (:class:`~.fusion.EvidenceMap`): it equals the centralised fusion
    (:func:`~.fusion.fuse_records`) cell for cell once all has arrived.
``roam`` (the baseline, :mod:`.roam`)
    ROAM's rule as its code does it; every period the full tree, at most one fusion per period.
``laplacian`` (:mod:`.laplacian`)
    The paper's consensus step on evidence with Metropolis-Hastings weights, scaled by N.

Frames: the node calls :meth:`MapConsensus.set_frame` with the root robot of the world frame
the robot's submap poses are in (its own id until it is aligned); a peer's evidence is applied
only while the peer's poses are in the same frame, and kept (not dropped) until then.
Neighbours: :meth:`MapConsensus.set_neighbours`; messages from any other robot are ignored.
Whatever the mode, ``roam_bytes`` counts what ROAM would have sent: 36 B per node of the robot's
tree every ``roam_period`` (its ROAM tree in ``roam`` mode, its team map otherwise).
"""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.maps import MapState, MapVersions, RoamMap, SubmapEvidence, SubmapPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.acks import EVIDENCE, POSES, Acks, Send
from kimera_multi_py.mapshare.fusion import EvidenceMap, Key, octree_cells, view_rows
from kimera_multi_py.mapshare.held import MAX_VERSION, HeldSubmap, marks_for
from kimera_multi_py.mapshare.laplacian import LaplacianState
from kimera_multi_py.mapshare.roam import ROAM_NODE_BYTES, RoamFusion
from kimera_multi_py.mapshare.wire import pack_cells, unpack_cells

log = logging.getLogger(__name__)

MODES = ("roam", "exact", "laplacian")
MAP_MESSAGES = (SubmapEvidence, SubmapPoses, MapVersions, MapState, RoamMap)  # what a MapConsensus handles


@dataclass
class MapConsensusParams:
    """A robot's map consensus knobs; the mode is the node's (``node.map_consensus``)."""

    mode: str = "exact"
    """roam, exact or laplacian."""
    period: float = 1.0
    """Seconds between steps that publish."""
    summary_every: int = 5
    """Periods between unchanged MapVersions summaries."""
    roam_period: float = 5.0
    """ROAM's publishing period (s; its demo branch), also for ``roam_bytes``."""
    roam_weight: float = 0.2
    """ROAM: w of h_i <- clip(h_i + w h_j) (its demo branch)."""
    roam_top_k: int = 3
    """ROAM: labels kept per cell (the rest summed as "others")."""
    roam_clamp: float = 5.0
    """ROAM: every fused log-odds entry is clamped to plus or minus this."""
    epsilon: float = 1.0
    """Laplacian consensus: step size."""
    refresh_every: int = 10
    """Laplacian consensus: a full state every this many rounds."""
    hold: float = 10.0
    """Exact: seconds between versions of the robot's newest submap while it still grows (its
    cells change with every scan, so each version would carry most of them again), counted from
    when the submap appeared; a submap that is no longer the newest gets its last version at
    once. With a hold as long as a submap lasts, most submaps travel once. 0: every period."""
    palette_rows: bool = True
    """Exact: evidence rows as a palette of distinct rows and an index per cell (:mod:`.wire`);
    False: the plain rows (the format before, to measure what the palette saves)."""

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"map consensus mode must be one of {MODES}, got {self.mode!r}")
        if not (self.period > 0 and self.roam_period > 0):
            raise ValueError("map consensus periods must be positive")
        if not self.hold >= 0:
            raise ValueError(f"map consensus hold must be non-negative, got {self.hold}")


class MapConsensus:
    """One robot's map consensus (see the module docstring)."""

    def __init__(self, robot: int, local: SubmapMap, params: MapConsensusParams | None = None,
                 team_size: int = 1) -> None:
        self.robot = int(robot)
        self.local = local
        self.params = params or MapConsensusParams()
        self.mode = self.params.mode
        self.frame = self.robot
        self.neighbours: set[int] = set()
        self.team_size = int(team_size)
        self.k = local.num_classes
        self.roam_bytes = 0
        self.rounds = 0
        self.ignored: Counter[str] = Counter()
        self._now = -np.inf
        self._next = -np.inf
        self._next_roam = -np.inf
        # exact
        self.team = EvidenceMap(local.template)
        self.held: dict[Key, HeldSubmap] = {}
        self.poses: dict[int, tuple[SubmapPoses, float]] = {}  # source -> (latest table, got)
        self._own_table: tuple[int, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._pose_version = 0
        self._nbr: dict[int, tuple[dict[Key, int], dict[int, int], float]] = {}
        self._nbr_frame: dict[int, int] = {}  # each neighbour's team frame, as its summary said
        self.acks = Acks(self.robot, wait=2.0 * self.params.period)
        self._sent: dict[Key, Send] = {}
        self._sent_poses: dict[int, Send] = {}
        self._summary: tuple[bytes, int] | None = None  # last content, periods since sent
        # roam / laplacian
        self.roam = RoamFusion(local.template, self.params.roam_weight, self.params.roam_top_k,
                               self.params.roam_clamp) if self.mode == "roam" else None
        self._roam_fused_this_period = False
        self.lap = LaplacianState(self.k + 1, self.params.epsilon,
                                  self.params.refresh_every) if self.mode == "laplacian" else None
        self._lap_frames: dict[int, int] = {}
        self._team_cache: SemanticOctree | None = None

    # ---- what the node tells us ------------------------------------------------------------
    def set_neighbours(self, ids: set[int] | list[int] | tuple[int, ...]) -> None:
        """The robots this one can hear and reach directly (its one-hop neighbours)."""
        self.neighbours = {int(i) for i in ids} - {self.robot}

    def set_frame(self, frame: int) -> None:
        """The root robot of the world frame the robot's submap poses are now in."""
        frame = int(frame)
        if frame == self.frame:
            return
        self.frame = frame
        if self.mode == "exact":
            for src in self.poses:
                self._activate(src)
        elif self.lap is not None:
            self.lap.reset()

    def set_team_size(self, n: int) -> None:
        """N, the number of robots whose evidence is averaged (laplacian mode's scale)."""
        self.team_size = max(1, int(n))

    # ---- messages in -----------------------------------------------------------------------
    def handle(self, msg: Message) -> None:
        """Absorb one message; raises :class:`MessageError` on inconsistent content."""
        if msg.robot == self.robot:
            return
        if msg.robot not in self.neighbours:
            self.ignored["not_neighbour"] += 1
            return
        if isinstance(msg, SubmapEvidence) and self.mode == "exact":
            self.acks.received(EVIDENCE, msg.robot, msg.seq)
            self._on_evidence(msg)
        elif isinstance(msg, SubmapPoses) and self.mode == "exact":
            self.acks.received(POSES, msg.robot, msg.seq)
            self._on_poses(msg)
        elif isinstance(msg, MapVersions) and self.mode == "exact":
            self._on_versions(msg)
        elif isinstance(msg, RoamMap) and self.roam is not None:
            if msg.frame != self.frame or self._roam_fused_this_period:
                self.ignored["roam_dropped"] += 1
                return
            self.roam.fuse(msg)
            self._roam_fused_this_period = True
            self._team_cache = None
        elif isinstance(msg, MapState) and self.lap is not None:
            if msg.frame != self.frame:
                self.ignored["other_frame"] += 1
                return
            self.lap.handle(msg)

    def _on_evidence(self, msg: SubmapEvidence) -> None:
        if msg.classes != self.k:
            raise MessageError(f"SubmapEvidence.classes: expected {self.k} classes, got {msg.classes}")
        if msg.base >= msg.version:
            raise MessageError(f"SubmapEvidence: base {msg.base} not below version {msg.version}")
        if msg.version > MAX_VERSION:
            raise MessageError(f"SubmapEvidence: version {msg.version} out of range")
        if msg.source == self.robot:
            return
        key = (msg.source, msg.submap)
        h = self.held.get(key)
        have = h.version if h is not None else 0
        if msg.version <= have:
            self.ignored["evidence_duplicate"] += 1
            return
        if msg.base > have:
            self.ignored["evidence_gap"] += 1  # the summary asks for it again
            return
        codes, values = unpack_cells(msg.payload, msg.cells, msg.classes, "SubmapEvidence.payload")
        rows = np.zeros((len(codes), self.k + 1), np.int32)
        rows[:, 1:] = values
        if h is None:
            h = self.held[key] = HeldSubmap.empty(self._now)
        self._merge(key, h, codes, rows, msg.version)
        h.version, h.got, h.via = msg.version, self._now, (msg.robot, msg.seq)

    def _on_poses(self, msg: SubmapPoses) -> None:
        if msg.source == self.robot:
            self._own_version_seen(msg.version)
            return
        old = self.poses.get(msg.source)
        if old is not None and msg.version <= old[0].version:
            self.ignored["poses_duplicate"] += 1
            return
        self.poses[msg.source] = (msg, self._now)
        keys = [(msg.source, sid) for sid in msg.submaps.tolist()]
        if msg.frame != self.frame:
            for key in keys:
                self.team.set_active(key, False)
        self.team.set_poses(zip(keys, msg.T_ref, msg.T, strict=True))
        self._activate(msg.source)

    def _activate(self, src: int) -> None:
        entry = self.poses.get(src)
        if entry is None:
            return
        active = entry[0].frame == self.frame
        for sid in entry[0].submaps.tolist():
            self.team.set_active((src, sid), active)

    def _on_versions(self, msg: MapVersions) -> None:
        versions = {(int(s), int(m)): int(v) for s, m, v in
                    zip(msg.sources.tolist(), msg.submaps.tolist(), msg.versions.tolist(), strict=True)}
        pose_versions = dict(zip(msg.pose_sources.tolist(), msg.pose_versions.tolist(), strict=True))
        self.acks.on_summary(msg.robot, msg.ack_robots, msg.ack_evidence, msg.ack_poses, self._now)
        self._nbr[msg.robot] = (versions, pose_versions, self._now)
        self._nbr_frame[msg.robot] = int(msg.frame)
        self._own_version_seen(int(pose_versions.get(self.robot, 0)))

    def _own_version_seen(self, version: int) -> None:
        """A neighbour holds this robot's own pose table at ``version``. A robot that restarted
        (the map consensus is not checkpointed) counts its table's versions from 0 again, and its
        neighbours would ignore the new tables as duplicates of the old ones they hold: versions
        continue above every one a neighbour reports, and the current table goes out afresh."""
        if version > self._pose_version:
            self._pose_version = version
            self._own_table = None

    # ---- the step --------------------------------------------------------------------------
    def step(self, now: float) -> list[Message]:
        """Publish what is due at time ``now`` (seconds); nothing between periods."""
        self._now = float(now)
        out: list[Message] = []
        if self._now >= self._next_roam:
            self._next_roam = self._now + self.params.roam_period
            self._roam_fused_this_period = False
            if self.roam is not None:
                self.roam.absorb_own(self.local)
                msg = self.roam.message(self.robot, self.rounds, self.frame)
                self.roam_bytes += ROAM_NODE_BYTES * msg.nodes
                out.append(msg)
            else:
                self.roam_bytes += ROAM_NODE_BYTES * self.team_map.num_nodes
        if self._now < self._next:
            return out
        self._next = self._now + self.params.period
        self.rounds += 1
        self._team_cache = None
        if self.mode == "exact":
            self._snapshot_own()
            out += self._exact_messages()
        elif self.lap is not None:
            self.lap.mix(sorted(self.neighbours))
            self.lap.absorb_own(self.local)
            out += self.lap.message(self.robot, self.frame, len(self.neighbours))
        elif self.roam is not None:
            self.roam.absorb_own(self.local)
        return out

    def _snapshot_own(self) -> None:
        """Take new versions of the own submaps (version = scans integrated) and the pose table.

        The newest submap, still growing, gets a version ``hold`` seconds after it appeared and
        at most every ``hold`` seconds after that: its cells change with every scan, and each
        version goes out to the neighbours at once."""
        newest = max(self.local.submaps, default=None)
        for sid, s in sorted(self.local.submaps.items()):
            key = (self.robot, sid)
            h = self.held.get(key)
            if h is None:
                h = self.held[key] = HeldSubmap.empty(self._now)
            if sid == newest and self._now - h.got < self.params.hold:
                continue
            if s.num_scans > h.version:
                h_codes, h_rows = self.team.record(key)
                pos = np.searchsorted(h_codes, s.codes).clip(max=max(len(h_codes) - 1, 0))
                old = np.zeros(len(s.codes), np.bool_)
                if len(h_codes):
                    old = h_codes[pos] == s.codes
                changed = ~old
                changed[old] = np.any(h_rows[pos[old]] != s.rows[old], axis=1)
                self._merge(key, h, s.codes[changed], s.rows[changed], s.num_scans)
                h.version, h.got = s.num_scans, self._now
        own = [((self.robot, sid), s.T_ref, s.T) for sid, s in sorted(self.local.submaps.items())]
        self.team.set_poses(own)
        for key, _, _ in own:
            self.team.set_active(key, True)
        sids = np.array(sorted(self.local.submaps), dtype=np.int64)
        T_ref = np.array([self.local.submaps[i].T_ref for i in sids.tolist()]).reshape(-1, 4, 4)
        T = np.array([self.local.submaps[i].T for i in sids.tolist()]).reshape(-1, 4, 4)
        old_t = self._own_table
        if old_t is None or old_t[0] != self.frame or not (
                np.array_equal(old_t[1], sids) and np.array_equal(old_t[2], T_ref) and np.array_equal(old_t[3], T)):
            self._own_table = (self.frame, sids, T_ref, T)
            self._pose_version += 1
            msg = SubmapPoses(robot=self.robot, source=self.robot, version=self._pose_version, frame=self.frame,
                              submaps=sids, T_ref=T_ref, T=T)
            self.poses[self.robot] = (msg, self._now)

    def _merge(self, key: Key, h: HeldSubmap, codes: np.ndarray, rows: np.ndarray, version: int) -> None:
        """Set cells of a held submap (sorted unique ``codes``): rows into the team's record,
        ``version`` into the marks of the cells it changes."""
        if len(codes) == 0:
            return
        held = self.team.cells(key)
        pos = np.searchsorted(held, codes)
        known = pos < len(held)
        known[known] = held[pos[known]] == codes[known]
        h.marks = marks_for(h.marks, version)
        h.marks[pos[known]] = version
        if not known.all():
            h.marks = np.insert(h.marks, pos[~known], version)
        self.team.set_cells(key, codes, rows)

    def _bases(self, nbrs: list[int], stream: int, source: int, want: int, got: float, via: tuple[int, int],
               sent: Send | None, reported: Callable[[int], int]) -> list[int]:
        """The versions of the neighbours that should be sent version ``want`` of a source's data
        (``stream``), which arrived here at ``got`` in the message ``via`` (sender, seq).

        A neighbour holds what its summary says, or what we sent it while that send has not
        gone through (:meth:`.acks.Acks.through`: it may wait in a slow link's queue, and sending
        it again would only lengthen the queue). A robot's own data goes out at once to whoever
        lacks it; a relay waits for the neighbour's summary, newer than our copy, to say it still
        lacks it after the copy the neighbour had from the same sender went through (the
        neighbour may have it from the source directly, its link slower than ours). Lost
        messages show up as a summary past them that still lacks what was sent, and go again.
        """
        out = []
        for k in nbrs:
            if k == source:
                continue
            t = self._nbr[k][2] if k in self._nbr else -np.inf
            have = reported(k)
            if sent is not None and sent.version > have and k in sent.to and not self.acks.through(
                    k, stream, self.robot, sent.seq, sent.t, t, sent.count):
                have = sent.version
            if have >= want:
                continue
            if source == self.robot or (t > got and (via[0] < 0 or not self.acks.hears(k, stream, via[0])
                                                     or self.acks.through(k, stream, via[0], via[1], got, t))):
                out.append(have)
        return out

    def _send(self, sent: dict, item: Key | int, stream: int, version: int, nbrs: list[int]) -> int:
        """Record a send of ``version`` of ``item``; its ``seq``."""
        old = sent.get(item)
        seq = self.acks.stamp(stream, self._now)
        count = old.count + 1 if old is not None and old.version == version else 1
        sent[item] = Send(version, self._now, seq, frozenset(nbrs), count)
        return seq

    def _reported(self, key: Key) -> Callable[[int], int]:
        return lambda k: self._nbr[k][0].get(key, 0) if k in self._nbr else 0

    def _reported_poses(self, src: int) -> Callable[[int], int]:
        return lambda k: self._nbr[k][1].get(src, 0) if k in self._nbr else 0

    def _exact_messages(self) -> list[Message]:
        out: list[Message] = []
        nbrs = sorted(self.neighbours)
        for src, (table, got) in sorted(self.poses.items()):
            via = (table.robot, table.seq) if src != self.robot else (-1, 0)
            if self._bases(nbrs, POSES, src, table.version, got, via, self._sent_poses.get(src),
                           self._reported_poses(src)):
                seq = self._send(self._sent_poses, src, POSES, table.version, nbrs)
                out.append(SubmapPoses(robot=self.robot, source=table.source, version=table.version,
                                       frame=table.frame, submaps=table.submaps, T_ref=table.T_ref, T=table.T,
                                       seq=seq))
        for key, h in sorted(self.held.items()):
            if h.version == 0:
                continue
            bases = self._bases(nbrs, EVIDENCE, key[0], h.version, h.got, h.via, self._sent.get(key),
                                self._reported(key))
            if bases:
                base = min(bases)
                sel = h.marks > base
                codes, rows = self.team.record(key)
                seq = self._send(self._sent, key, EVIDENCE, h.version, nbrs)
                out.append(SubmapEvidence(robot=self.robot, source=key[0], submap=key[1], base=base,
                                          version=h.version, cells=int(sel.sum()), classes=self.k,
                                          payload=pack_cells(codes[sel], rows[sel, 1:].astype(np.int16),
                                                             self.params.palette_rows), seq=seq))
        summary = self._versions()
        content = b"".join(a.tobytes() for a in (
            summary.sources, summary.submaps, summary.versions, summary.pose_sources, summary.pose_versions,
            summary.ack_robots, summary.ack_evidence, summary.ack_poses)) + bytes([self.frame % 256])
        if self._summary is None or self._summary[0] != content or self._summary[1] + 1 >= self.params.summary_every:
            self._summary = (content, 0)
            if nbrs:
                out.append(summary)
        else:
            self._summary = (content, self._summary[1] + 1)
        return out

    def _versions(self) -> MapVersions:
        keys = sorted(k for k, h in self.held.items() if h.version > 0)
        srcs = sorted(self.poses)
        ack_robots, ack_evidence, ack_poses = self.acks.fields()
        return MapVersions(
            robot=self.robot, frame=self.frame,
            sources=np.array([k[0] for k in keys], np.int32), submaps=np.array([k[1] for k in keys], np.int64),
            versions=np.array([self.held[k].version for k in keys], np.int64),
            pose_sources=np.array(srcs, np.int32),
            pose_versions=np.array([self.poses[s][0].version for s in srcs], np.int64),
            ack_robots=ack_robots, ack_evidence=ack_evidence, ack_poses=ack_poses)

    def heard(self) -> set[int]:
        """Robots whose evidence, pose table or version summary this robot holds (itself too)."""
        return {k[0] for k in self.held} | set(self.poses) | set(self._nbr) | {self.robot}

    def gaps(self, robots: Iterable[int]) -> dict[int, dict[str, object]]:
        """Where this robot's held evidence and pose tables differ from each robot's last version
        summary (``exact`` mode): per robot with a difference, the submaps and pose tables it
        holds newer (``behind``: we lack them) or older (``ahead``), a frame that differs, or that
        no summary came. Empty: every robot holds what we hold, so our team maps are the same."""
        mine = {k: h.version for k, h in self.held.items() if h.version > 0}
        my_poses = {s: t.version for s, (t, _) in self.poses.items()}
        out: dict[int, dict[str, object]] = {}
        for r in sorted(set(robots) - {self.robot}):
            if r not in self._nbr:
                out[r] = {"summary": "none received"}
                continue
            versions, pose_versions, _ = self._nbr[r]
            gap: dict[str, object] = {}
            behind = sorted(k for k, v in versions.items() if mine.get(k, 0) < v)
            ahead = sorted(k for k, v in mine.items() if versions.get(k, 0) < v)
            poses_behind = sorted(s for s, v in pose_versions.items() if my_poses.get(s, 0) < v)
            poses_ahead = sorted(s for s, v in my_poses.items() if pose_versions.get(s, 0) < v)
            for name, items in (("submaps_behind", behind), ("submaps_ahead", ahead),
                                ("pose_tables_behind", poses_behind), ("pose_tables_ahead", poses_ahead)):
                if items:
                    gap[name] = [list(k) if isinstance(k, tuple) else k for k in items]
            if self._nbr_frame.get(r, self.frame) != self.frame:
                gap["frame"] = {"mine": self.frame, "theirs": self._nbr_frame[r]}
            if gap:
                out[r] = gap
        return out

    # ---- results ---------------------------------------------------------------------------
    @property
    def nbytes(self) -> int:
        """Bytes the map consensus holds beyond the robot's own map: the evidence held per
        submap and the team's evidence store (docs/performance.md)."""
        held = sum(h.marks.nbytes for h in self.held.values())
        return int(held + self.team.nbytes) if self.mode == "exact" else int(held)

    @property
    def team_map(self) -> SemanticOctree:
        """The robot's team map (an octree; do not change it)."""
        if self.mode == "exact":
            return self.team.octree
        if self.roam is not None:
            return self.roam.tree
        if self._team_cache is None:
            codes, rows = self.team_cells()
            tree = self.local.template.empty_like()
            tree.set_cells(codes, rows)
            self._team_cache = tree
        return self._team_cache

    def frame_sources(self, frame: int) -> list[int]:
        """The other robots whose latest pose table is in the frame rooted at ``frame`` (exact mode)."""
        if self.mode != "exact":
            return []
        return sorted(src for src, (table, _) in self.poses.items() if table.frame == frame and src != self.robot)

    def frame_cells(self, frame: int, sources: list[int] | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """The evidence of ``sources`` (default: every other robot whose poses are in the frame
        rooted at ``frame``), fused: finest-level codes and clamped int16 rows, as a tree holds
        them. None outside exact mode, where evidence is not kept per source."""
        if self.mode != "exact":
            return None
        chosen = self.frame_sources(frame) if sources is None else sources
        keys = [(src, sid) for src in chosen if src in self.poses for sid in self.poses[src][0].submaps.tolist()]
        codes, rows = self.team.fused(keys)
        return codes, view_rows(self.team.template, rows)

    def team_cells(self) -> tuple[np.ndarray, np.ndarray]:
        """Every finest-level cell of the team map: sorted codes and int16 rows (as the tree holds them)."""
        if self.mode == "exact":
            codes, rows, _ = self.team.evidence()
            return codes, _compressed(self.team.template, view_rows(self.team.template, rows))
        if self.roam is not None:
            return octree_cells(self.roam.tree)
        assert self.lap is not None
        codes, rows, _ = self.lap.team_rows(self.team_size)
        return codes, _compressed(self.local.template, view_rows(self.local.template, rows))


def _compressed(tree: SemanticOctree, rows: np.ndarray) -> np.ndarray:
    return tree._compress(rows) if tree.top_k is not None else rows


def get_map_consensus(robot: int, local: SubmapMap, mode: str = "exact", team_size: int = 1,
                      base: MapConsensusParams | None = None, **params: float | int | str) -> MapConsensus:
    """A robot's map consensus in ``mode`` (``roam``, ``exact`` or ``laplacian``), with the knobs of
    ``base`` (default: the defaults) and ``params``."""
    knobs = dataclasses.replace(base or MapConsensusParams(), mode=mode, **params)  # type: ignore[arg-type]
    return MapConsensus(robot, local, knobs, team_size)
