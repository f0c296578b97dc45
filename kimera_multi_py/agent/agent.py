"""The per-robot Agent: pure logic, no I/O (docs/architecture.md, §6).

``Agent.process_keyframe(kf)`` and ``Agent.handle(msg)`` return the messages to send; a
runtime (:mod:`.node`, :class:`~kimera_multi_py.workflow.simulate.SimRunner`) moves them. The agent
owns:

* its pose graph: dead-reckoned poses in its own odometry frame (never changed, used by PCM),
  the current estimate (moved by PGO, in the team frame once aligned), odometry edges, scan
  registration edges (:class:`~kimera_multi_py.mapping.scan_odometry.ScanOdometry`: each scan
  registered to the last keyframes' scans; its Hessian is the factor's information, zero in
  degenerate directions; the estimate chains the fusion of both) and intra-robot loop closures;
* submaps feeding a semantic octree (:class:`SubmapMap`) and an object map, both re-anchored
  exactly when PGO moves the submaps, and a people tracker (:mod:`kimera_multi_py.people`, fed by
  the dynamic points the octree masks out; docs/algorithms/people.md), moved the same way;
* its loop-closure front end, which works in the robot's own odometric frame (the chained
  registration-refined steps) and never reads the team estimate: what it verifies depends on the
  robot's sensor data and its peers' messages, not on when or how the back end ran, so the
  distributed and centralised modes gather the same evidence. Every ``descriptor_every``
  keyframes the objects seen over the last ``descriptor_window`` keyframes (in a second object
  map, kept in the odometric frame) form a constellation in the keyframe's frame; its
  descriptor is published (only the descriptor). A robot compares other robots' descriptors
  with its own; for a pair of robots the lower id verifies (within a budget of candidates per
  period), fetching the full constellation with a query, verifying it geometrically (max
  clique + Umeyama, then GICP on the fetched cloud) and passing every verified closure of the
  pair through PCM. The accepted set is published as ``LoopClosures``; both robots then hold
  the edges for PGO. Intra-robot closures come from constellations and from places: an older
  keyframe near this one by odometry is registered against it (:meth:`Agent._revisits`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from kimera_multi_py.agent import pose_graph
from kimera_multi_py.agent.closures import Closure, Constellation, LoopClosureStats
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.comms.clouds import COMPACT, RAW, pack_cloud
from kimera_multi_py.comms.messages.base import Message
from kimera_multi_py.comms.messages.closures import (
    KeyframeDescriptor,
    KeyframeOdometry,
    LoopClosureReply,
    LoopClosureRequest,
    LoopClosures,
    LoopClosuresAck,
)
from kimera_multi_py.comms.messages.pgo import PublicPoses
from kimera_multi_py.comms.messages.team import AgentState
from kimera_multi_py.core.geometry import inverse, so3_log, transform_points
from kimera_multi_py.core.ids import MAX_AGENT_ID
from kimera_multi_py.core.keyframe import KeyframeInput
from kimera_multi_py.core.posegraph import robot_key, split_key
from kimera_multi_py.core.semantics import NUM_CLASSES, OBJECT_CLASSES, class_id
from kimera_multi_py.frontend.loop_closure import (
    DescriptorSpec,
    constellation_descriptor,
    similarity,
    verify,
    voxel_centroids,
    voxel_downsample,
)
from kimera_multi_py.frontend.pcm import odometry_consistent_path, pcm
from kimera_multi_py.mapping.config import get_object_map, get_submap_map
from kimera_multi_py.mapping.floor import FloorReference
from kimera_multi_py.mapping.heading import HeadingReference
from kimera_multi_py.mapping.registration import ScanRegistration
from kimera_multi_py.mapping.scan_odometry import ScanOdometry
from kimera_multi_py.people.tracking import PeopleTracker
from kimera_multi_py.pgo.local_graph import LocalGraph

log = logging.getLogger(__name__)

_OBJECT_IDS = np.array([class_id(c) for c in OBJECT_CLASSES])
_CLASS_TO_SLOT = np.full(NUM_CLASSES + 1, -1)
_CLASS_TO_SLOT[_OBJECT_IDS] = np.arange(len(_OBJECT_IDS))
_FLOOR = class_id("floor")
_WALL = class_id("wall")
_FLOOR_CEILING = (_FLOOR, class_id("ceiling"))


class Agent:
    """One robot's SLAM front end and map (see the module docstring)."""

    def __init__(self, robot: int, team: tuple[int, ...] | None = None, params: AgentParams | None = None) -> None:
        self.robot = robot
        self.team = tuple(team) if team is not None else None  # None: whoever is present
        self.params = params or AgentParams()
        p = self.params
        self.spec = DescriptorSpec(num_classes=len(_OBJECT_IDS))
        self.map = get_submap_map(p.mapping)
        self.objects = get_object_map(p.mapping)
        # people: tracked from the dynamic points the map masks out, anchored in submaps like objects
        self.people = PeopleTracker(self.map.template.dynamic_classes, p.people)
        self.stamps: list[float] = []
        self.odometry: list[np.ndarray] = []
        self.steps: list[np.ndarray] = []  # the chained step: odometry fused with scan registration
        self.scan_odometry = (ScanOdometry(ScanRegistration(p.reg_voxel, p.registration_stages(),
                                                           point_sigma=p.reg_point_sigma,
                                                           information_scale=p.reg_information_scale),
                                           p.odom_information(), p.reg_window, p.reg_min_ratio, p.reg_gate,
                                           FloorReference() if p.floor_reference else None,
                                           HeadingReference() if p.heading_reference else None)
                              if p.registration else None)
        self.closure_registration = ScanRegistration(p.cloud_voxel, p.closure_correspondence,
                                                     point_sigma=p.reg_point_sigma)
        self.front_end_seconds = 0.0  # wall time in process_keyframe (a machine measure)
        self.dead_reckoning: list[np.ndarray] = []  # own frame, fixed
        # the front end's frame: the chained steps (odometry fused with scan registration), own
        # frame, never moved by PGO; with the place objects below, the front end reads no estimate
        self.odometric: list[np.ndarray] = []
        self.place_objects = get_object_map(p.mapping)  # objects in the odometric frame (descriptors)
        self.poses: list[np.ndarray] = []  # current estimate (team frame once aligned)
        self.submap_of: list[int] = []
        self.kf_landmarks: list[list[int]] = []
        self.kf_clouds: list[tuple[np.ndarray, np.ndarray]] = []  # downsampled hits, sensor frame
        self.constellations: dict[int, Constellation] = {}
        self.peer_descriptors: dict[int, list[tuple[int, np.ndarray]]] = {}
        self.closures: dict[int, list[Closure]] = {}  # verified by me, per peer (self for intra)
        self.inter_edges: dict[tuple[int, int, int], tuple[np.ndarray, int]] = {}
        # (own_kf, peer, peer_kf) -> (Z own<-peer, inliers): every accepted inter-robot edge
        self.robot_graph: set[tuple[int, int]] = set()
        self.stats = LoopClosureStats()
        self._pending: dict[int, tuple[int, int, int]] = {}  # request id -> (peer, peer_kf, own_kf)
        self._request_id = 0
        self._budget: dict[int, list[float]] = {}
        self._batch: dict[int, int] = {}  # peer -> batches of closures sent
        self._peer_batch: dict[int, int] = {}  # peer -> newest batch of its closures received

    # ---- keyframes ------------------------------------------------------------------------
    @property
    def num_keyframes(self) -> int:
        return len(self.poses)

    def process_keyframe(self, kf: KeyframeInput) -> list[Message]:
        """Integrate one keyframe; return the messages to publish."""
        if kf.index != self.num_keyframes:
            raise ValueError(f"robot {self.robot}: keyframe {kf.index} out of order "
                             f"(expected {self.num_keyframes})")
        t0 = time.perf_counter()
        odom = np.eye(4) if kf.index == 0 else np.asarray(kf.odometry, dtype=float)
        if not np.all(np.isfinite(odom)):
            raise ValueError(f"robot {self.robot}: non-finite odometry at keyframe {kf.index}")
        hits = np.asarray(kf.hit, dtype=bool)
        static = hits & ~np.isin(kf.labels, self.map.template.dynamic_classes)
        so = self.scan_odometry
        floor = kf.points[hits & (kf.labels == _FLOOR)] if so is not None and so.floor is not None else None
        walls = kf.points[hits & (kf.labels == _WALL)] if so is not None and so.heading is not None else None
        step = odom if so is None else so.step(kf.index, odom, kf.points[static], floor, walls)
        dr = odom.copy() if kf.index == 0 else self.dead_reckoning[-1] @ odom
        pose = odom.copy() if kf.index == 0 else self.poses[-1] @ step
        fe = odom.copy() if kf.index == 0 else self.odometric[-1] @ step
        self.stamps.append(kf.stamp)
        self.odometry.append(odom)
        self.steps.append(step)
        self.dead_reckoning.append(dr)
        self.poses.append(pose)
        self.odometric.append(fe)
        # mapping: a new submap every keyframes_per_submap keyframes, anchored at its first pose
        sid = kf.index // self.params.mapping.keyframes_per_submap
        if sid not in self.map.submaps:
            if sid:  # a submap closed: fuse object fragments an occluder split in every view
                self.objects.merge_fragments(self.map.octree)
            self.map.new_submap(sid, pose)
            self.objects.set_submap_pose(sid, pose)
            self.people.set_submap_pose(sid, pose)
            self.place_objects.set_submap_pose(sid, fe)  # never moved (nor fragment-merged: no octree here)
        self.submap_of.append(sid)
        T_sub = inverse(self.map.submaps[sid].T) @ pose
        self.map.integrate(sid, T_sub, kf.points, kf.labels, kf.max_range)
        self.objects.update(transform_points(pose, kf.points[hits]), kf.labels[hits], sid, kf.index)
        if self.params.people.enabled:
            self.people.update(kf.index, kf.stamp, sid, transform_points(pose, kf.points[hits]), kf.labels[hits],
                               pose[:3, 3])
        seen = self.place_objects.update(transform_points(fe, kf.points[hits]), kf.labels[hits], sid, kf.index)
        self.kf_landmarks.append(seen)
        # the semantic cloud for ICP: walls and objects (floor and ceiling add bytes, not constraints)
        walls = static & ~np.isin(kf.labels, _FLOOR_CEILING)
        self.kf_clouds.append(voxel_downsample(kf.points[walls], kf.labels[walls], self.params.cloud_voxel))
        out: list[Message] = []
        if self.params.server is not None:  # the server's odometry factor: the registration-refined step
            out.append(KeyframeOdometry(robot=self.robot, keyframes=np.array([kf.index], dtype=np.int64),
                                        odometry=step[None]))
        if kf.index % self.params.descriptor_every == 0:
            out += self._revisits(kf.index)
            c = self._constellation(kf.index)
            if c is not None:
                self.constellations[kf.index] = c
                out.append(KeyframeDescriptor(robot=self.robot, keyframe=kf.index, stamp=kf.stamp,
                                              kind="objects", descriptor=c.descriptor))
                out += self._intra_closures(c)
                for peer, descs in sorted(self.peer_descriptors.items()):
                    for peer_kf, d in descs:
                        out += self._maybe_request(peer, peer_kf, d, kf.stamp, own=[c])
        self.front_end_seconds += time.perf_counter() - t0
        return out

    def _constellation(self, k: int) -> Constellation | None:
        window = self.kf_landmarks[max(0, k - self.params.descriptor_window + 1): k + 1]
        ids = sorted({i for ids in window for i in ids if i in self.place_objects.landmarks})
        lms = [self.place_objects.landmarks[i] for i in ids]
        lms = [lm for lm in lms if lm.num_observations >= 2]
        if len(lms) < self.params.min_objects:
            return None
        xyz_world = np.array([lm.ref_position for lm in lms])
        xyz = transform_points(inverse(self.odometric[k]), xyz_world)
        classes = np.array([lm.label for lm in lms])
        desc = constellation_descriptor(xyz, _CLASS_TO_SLOT[classes], self.spec)
        cloud, cloud_labels = self._window_cloud(k)
        return Constellation(k, self.stamps[k], xyz, classes, desc, cloud, cloud_labels)

    def _window_cloud(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The semantic cloud of the ``descriptor_window`` keyframes up to ``k``, in ``k``'s frame."""
        first = max(0, k - self.params.descriptor_window + 1)
        inv = inverse(self.odometric[k])
        parts = [transform_points(inv @ self.odometric[j], self.kf_clouds[j][0]) for j in range(first, k + 1)]
        labels = np.concatenate([self.kf_clouds[j][1] for j in range(first, k + 1)])
        return voxel_downsample(np.concatenate(parts), labels, self.params.cloud_voxel)

    def _revisits(self, k: int) -> list[Message]:
        """Intra-robot closures by place, not by appearance: the nearest older keyframe (by
        odometry, at least ``intra_min_gap`` back, facing within ``revisit_angle``) within
        ``revisit_radius`` is registered against this one (GICP on the windows' clouds) and, when
        the clouds overlap well, goes to PCM like any closure. Corridors and doorways have too
        few objects for a constellation, and twin rooms are never that close by odometry."""
        p = self.params
        if p.revisit_radius <= 0 or k < p.intra_min_gap:
            return []
        odo = self.odometric
        P = np.array(odo[: k - p.intra_min_gap + 1: p.descriptor_every])
        cos = np.einsum("ni,i->n", P[:, :3, 0], odo[k][:3, 0])
        d = np.linalg.norm(P[:, :3, 3] - odo[k][:3, 3], axis=1)
        d[cos < np.cos(p.revisit_angle)] = np.inf
        if not np.isfinite(d.min()) or d.min() > p.revisit_radius or not self._spend(self.robot, self.stamps[k]):
            return []
        old = int(np.argmin(d)) * p.descriptor_every
        self.stats.candidates += 1
        guess = inverse(odo[old]) @ odo[k]
        res = self.closure_registration.register(self._window_cloud(old)[0], self._window_cloud(k)[0], guess)
        step = None if res is None else inverse(guess) @ res.T
        max_t, max_r = p.icp_max_correction
        if (res is None or step is None or not res.converged or res.overlap < p.revisit_overlap
                or np.linalg.norm(step[:3, 3]) > max_t or np.linalg.norm(so3_log(step[:3, :3])) > max_r):
            self.stats.rejected_verification += 1
            return []
        self.stats.verified += 1
        return self._add_closure(self.robot, Closure(old, self.robot, k, res.T, res.inliers,
                                                     self.dead_reckoning[old], self.dead_reckoning[k]))

    # ---- loop closures --------------------------------------------------------------------
    def _verifier(self, peer: int) -> bool:
        return self.robot < peer

    def _spend(self, peer: int, stamp: float) -> bool:
        recent = [t for t in self._budget.get(peer, []) if stamp - t < self.params.budget_period]
        if len(recent) >= self.params.budget:
            self._budget[peer] = recent
            return False
        self._budget[peer] = recent + [stamp]
        return True

    def _maybe_request(self, peer: int, peer_kf: int, desc: np.ndarray, stamp: float,
                       own: list[Constellation] | None = None) -> list[Message]:
        """Request the peer keyframe's constellation if it resembles places of ours.

        Up to ``matches_per_query`` of our most similar places are tried, each at least
        ``distinct_places`` keyframes from the others: in identical rooms the best-scoring one
        is a coin toss, so every look-alike is verified and PCM / GNC decide between them.
        """
        if not self._verifier(peer):
            return []
        cands = own if own is not None else list(self.constellations.values())
        if not cands:
            return []
        sims = similarity(desc, np.stack([c.descriptor for c in cands]))
        done = {(c.own_kf, c.peer_kf) for c in self.closures.get(peer, [])}
        chosen: list[int] = []
        for i in np.argsort(-sims, kind="stable"):
            if sims[i] < self.params.min_similarity or len(chosen) >= self.params.matches_per_query:
                break
            k = cands[int(i)].keyframe
            if (k, peer_kf) in done or any(abs(k - c) < self.params.distinct_places for c in chosen):
                continue
            chosen.append(k)
        out: list[Message] = []
        for k in chosen:
            if not self._spend(peer, stamp):
                break
            self._request_id += 1
            self._pending[self._request_id] = (peer, peer_kf, k)
            self.stats.candidates += 1
            out.append(LoopClosureRequest(robot=self.robot, target=peer, request_id=self._request_id,
                                          keyframe=peer_kf, query_keyframe=k))
        return out

    def unanswered(self, peer: int) -> list[LoopClosureRequest]:
        """Our queries to ``peer`` that no reply answered (lost, or asked while it was out of
        reach), to ask again: a reply to any copy answers the request once."""
        return [LoopClosureRequest(robot=self.robot, target=peer, request_id=rid, keyframe=peer_kf,
                                   query_keyframe=own_kf)
                for rid, (p, peer_kf, own_kf) in sorted(self._pending.items()) if p == peer]

    def unanswered_requests(self) -> dict[int, int]:
        """Request id -> peer, of every query of ours no reply has answered yet."""
        return {rid: p for rid, (p, _, _) in self._pending.items()}

    def serve_keyframe(self, keyframe: int, request_id: int = 0, compact: bool = True) -> LoopClosureReply:
        """The constellation of one of our keyframes, for a peer's verification. ``compact``: the
        cloud as the closure registration sees it (one mean per registration voxel, packed
        small, :mod:`kimera_multi_py.comms.clouds`); else every kept point, raw."""
        c = self.constellations.get(keyframe)
        if c is None:
            return LoopClosureReply(robot=self.robot, request_id=request_id, keyframe=keyframe, found=False,
                                    pose=np.eye(4), num_points=0, cloud=pack_cloud(np.zeros((0, 3)), np.zeros(0)),
                                    object_centroids=np.zeros((0, 3), dtype=np.float32),
                                    object_classes=np.zeros(0, dtype=np.int32))
        if compact:
            points, labels = voxel_centroids(c.cloud, c.cloud_labels, self.closure_registration.voxel)
            cloud = pack_cloud(points, labels, COMPACT)
        else:
            points, labels = c.cloud, c.cloud_labels
            cloud = pack_cloud(points, labels, RAW)
        return LoopClosureReply(robot=self.robot, request_id=request_id, keyframe=keyframe, found=True,
                                pose=self.dead_reckoning[keyframe], num_points=len(points), cloud=cloud,
                                object_centroids=c.xyz.astype(np.float32),
                                object_classes=c.classes.astype(np.int32))

    def _verify(self, own: Constellation, xyz: np.ndarray, classes: np.ndarray, cloud: np.ndarray,
                cloud_labels: np.ndarray) -> tuple[np.ndarray, int] | None:
        """Objects first (max clique + Umeyama), then GICP of the fetched cloud onto ours from there."""
        v = verify(own.xyz, own.classes, np.asarray(xyz, float), np.asarray(classes), eps=self.params.verify_eps,
                   min_inliers=self.params.min_inliers)
        if not v.accepted:
            self.stats.rejected_verification += 1
            return None
        if not self._views_agree(v.T):  # before the registration: it would pair faces wrongly
            self.stats.rejected_verification += 1
            self.stats.rejected_view_angle += 1
            return None
        refined = self.closure_registration.register(own.cloud, np.asarray(cloud, dtype=float), v.T)
        confirmed = refined is not None and refined.converged and refined.overlap >= self.params.icp_min_overlap
        if confirmed:
            assert refined is not None
            step = inverse(v.T) @ refined.T
            max_t, max_r = self.params.icp_max_correction
            confirmed = bool(np.linalg.norm(step[:3, 3]) <= max_t and np.linalg.norm(so3_log(step[:3, :3])) <= max_r)
        if not confirmed:
            if self.params.require_registration:
                self.stats.rejected_verification += 1
                return None
            self.stats.verified += 1
            return v.T, v.num_inliers
        self.stats.verified += 1
        assert refined is not None
        return refined.T, v.num_inliers

    def _views_agree(self, Z: np.ndarray) -> bool:
        """Whether the two keyframes of relative pose ``Z`` face within ``max_view_angle`` of each
        other (the angle between their forward axes): views facing apart see opposite faces of
        the same objects, and registering one face to the other is off by the object's depth
        (docs/algorithms/frontend.md, "Views facing apart")."""
        return bool(Z[0, 0] >= np.cos(self.params.max_view_angle) - 1e-12)

    def _intra_closures(self, c: Constellation) -> list[Message]:
        """Intra-robot candidates against our own older keyframes (same machinery, no query)."""
        old = [o for k, o in self.constellations.items() if k <= c.keyframe - self.params.intra_min_gap]
        if not old:
            return []
        sims = similarity(c.descriptor, np.stack([o.descriptor for o in old]))
        best = int(np.argmax(sims))
        if sims[best] < self.params.min_similarity or not self._spend(self.robot, c.stamp):
            return []
        self.stats.candidates += 1
        o = old[best]
        res = self._verify(o, c.xyz, c.classes, c.cloud, c.cloud_labels)
        if res is None:
            return []
        return self._add_closure(self.robot, Closure(o.keyframe, self.robot, c.keyframe, res[0], res[1],
                                                     self.dead_reckoning[o.keyframe], self.dead_reckoning[c.keyframe]))

    def _add_closure(self, peer: int, closure: Closure) -> list[Message]:
        """Record a verified closure and re-run PCM over the pair; publish the accepted set."""
        group = self.closures.setdefault(peer, [])
        group.append(closure)
        before = [c.accepted for c in group]
        Z = np.stack([c.Z for c in group])
        A = np.stack([c.own_pose for c in group])
        B = np.stack([c.peer_pose for c in group])
        d = self.params.keyframe_distance
        pa = np.array([c.own_kf for c in group]) * d
        pb = np.array([c.peer_kf for c in group]) * d
        noise = self.params.pcm_noise()
        keep = pcm(Z, A, B, pa, pb, noise, min_size=self.params.pcm_min_size, groups=self.params.pcm_groups)
        if peer == self.robot:  # intra-robot: each closure must also agree with odometry alone,
            # its drift taken along the real path (a straight-line bound admits room-sized aliases)
            keep &= odometry_consistent_path(Z, np.array([c.own_kf for c in group]),
                                             np.array([c.peer_kf for c in group]), np.asarray(self.dead_reckoning),
                                             noise, d)
        for c, k in zip(group, keep, strict=True):
            c.accepted = bool(k)
        if [c.accepted for c in group] == before and not closure.accepted:
            return []
        accepted = [c for c in group if c.accepted]
        if peer != self.robot:
            self.inter_edges = {k: v for k, v in self.inter_edges.items() if k[1] != peer}
            for c in accepted:
                self.inter_edges[(c.own_kf, peer, c.peer_kf)] = (c.Z, c.inliers)
            if accepted:
                self.robot_graph.add((min(self.robot, peer), max(self.robot, peer)))
        self._batch[peer] = self._batch.get(peer, 0) + 1
        return [self.closures_message(peer)]

    def verified_inter(self) -> int:
        """Inter-robot closures this robot verified that PCM accepts now (its newest batches' sizes)."""
        return sum(sum(1 for c in cs if c.accepted) for peer, cs in self.closures.items() if peer != self.robot)

    def closures_message(self, peer: int) -> LoopClosures:
        """The closures with ``peer`` that PCM accepts now, as the newest batch."""
        accepted = [c for c in self.closures.get(peer, []) if c.accepted]
        n = len(accepted)
        return LoopClosures(
            robot=self.robot, peer=peer, batch=self._batch.get(peer, 0),
            keys_a=np.array([robot_key(self.robot, c.own_kf) for c in accepted], dtype=np.int64),
            keys_b=np.array([robot_key(peer, c.peer_kf) for c in accepted], dtype=np.int64),
            poses=np.stack([c.Z for c in accepted]) if n else np.zeros((0, 4, 4)),
            sigmas=np.tile(np.repeat(self.params.closure_sigmas, 3), (n, 1)),
            inliers=np.array([c.inliers for c in accepted], dtype=np.int32),
        )

    def handle(self, msg: Message) -> list[Message]:
        """React to a message from another robot; return the messages to send."""
        if msg.robot == self.robot:
            return []
        if msg.robot == self.params.server and self.params.server is not None:
            if isinstance(msg, PublicPoses):
                own = np.array([split_key(k)[0] == self.robot for k in msg.keys.tolist()], dtype=bool)
                if own.any():
                    self.apply_poses(np.array(msg.poses[own]))
            return []
        if (self.team is not None and msg.robot not in self.team) or not 0 <= msg.robot <= MAX_AGENT_ID:
            raise ValueError(f"robot {self.robot}: message from unknown robot {msg.robot}")
        if isinstance(msg, KeyframeDescriptor):
            known = self.peer_descriptors.setdefault(msg.robot, [])
            if any(k == msg.keyframe for k, _ in known):
                return []  # a re-send (the peer caught us up after a restart or a late join)
            known.append((msg.keyframe, np.array(msg.descriptor)))
            return self._maybe_request(msg.robot, msg.keyframe, msg.descriptor, msg.stamp)
        if isinstance(msg, LoopClosureReply):
            pending = self._pending.pop(msg.request_id, None)
            if pending is None or not msg.found or pending[:2] != (msg.robot, msg.keyframe):
                return []
            peer, peer_kf, own_kf = pending
            points, labels = msg.points()  # a corrupt cloud raises MessageError: the node counts it
            res = self._verify(self.constellations[own_kf], msg.object_centroids, msg.object_classes,
                               points, labels)
            if res is None:
                return []
            return self._add_closure(peer, Closure(own_kf, peer, peer_kf, res[0], res[1],
                                                   self.dead_reckoning[own_kf], np.array(msg.pose)))
        if isinstance(msg, AgentState):
            # the sender's robot graph: a pair whose closures we never heard of (lost on the way to
            # us, or accepted while we were cut off) still joins the robots' frames
            self.robot_graph.update((int(a), int(b)) for a, b in msg.pairs.tolist() if a != b)
            return []
        if isinstance(msg, LoopClosures):
            pair = (min(msg.robot, msg.peer), max(msg.robot, msg.peer))
            if len(msg.keys_a) and msg.robot != msg.peer:
                self.robot_graph.add(pair)
            if msg.peer != self.robot:
                return []
            ack: list[Message] = [LoopClosuresAck(robot=self.robot, peer=msg.robot, batch=msg.batch)]
            if msg.batch < self._peer_batch.get(msg.robot, -1):
                return ack  # an older batch re-sent late: the newer one stands
            self._peer_batch[msg.robot] = msg.batch
            self.inter_edges = {k: v for k, v in self.inter_edges.items() if k[1] != msg.robot}
            for ka, kb, Z, n in zip(msg.keys_a, msg.keys_b, msg.poses, msg.inliers, strict=True):
                own_kf = split_key(kb)[1]
                peer_kf = split_key(ka)[1]
                if own_kf < self.num_keyframes:
                    self.inter_edges[(own_kf, msg.robot, peer_kf)] = (inverse(np.array(Z)), int(n))
            return ack
        return []

    # ---- back end -------------------------------------------------------------------------
    def intra_edges(self) -> pose_graph.Edges:
        """Odometry, scan registrations and accepted intra-robot closures: ``(i, j, Z, info, is_odometry)``
        (:func:`.pose_graph.intra_edges`)."""
        so = self.scan_odometry
        return pose_graph.intra_edges(self.num_keyframes, self.steps, self.odometry, None if so is None else so.edges,
                                      self.closures.get(self.robot, []), self.params)

    def local_graph(self) -> LocalGraph:
        """What this robot contributes to distributed PGO, from its current estimate
        (:func:`.pose_graph.local_graph`)."""
        return pose_graph.local_graph(self.robot, self.team, self.poses, self.intra_edges(), self.inter_edges,
                                      self.robot_graph, self.params)

    def apply_poses(self, poses: np.ndarray) -> int:
        """Adopt optimised poses of the first keyframes; re-anchor the submaps and objects that moved.

        Keyframes newer than the optimised ones follow by chaining their odometry.
        """
        poses = np.asarray(poses, dtype=float)
        m = len(poses)
        if poses.shape[1:] != (4, 4) or not 0 < m <= self.num_keyframes or not np.all(np.isfinite(poses)):
            raise ValueError(f"robot {self.robot}: bad optimised poses of shape {poses.shape}")
        if m < self.num_keyframes:
            tail = [poses[-1]]
            for step in self.steps[m:]:
                tail.append(tail[-1] @ step)
            poses = np.concatenate([poses, np.array(tail[1:])])
        self.poses = list(poses)
        per = self.params.mapping.keyframes_per_submap
        anchors = {sid: poses[sid * per] for sid in self.map.submap_ids()}
        for sid, new in anchors.items():
            self.objects.set_submap_pose(sid, new)
            self.people.set_submap_pose(sid, new)
        return self.map.move_submaps(anchors)
