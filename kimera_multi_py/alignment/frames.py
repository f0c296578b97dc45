"""Robust frame alignment between two robots from their inter-robot measurements.

Each measurement between an own pose (own frame) and a neighbour pose (team frame) proposes one
frame transform ``T_team_own``. GNC-TLS rotation averaging (chordal) picks the rotation and the
rotation inliers; translation averaging (GNC-TLS again) over those inliers gives the
translation. At least ``min_inliers`` consistent measurements are needed.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.core.geometry import inverse, make_pose, so3_log
from kimera_multi_py.core.robust import MU_STEP, GncSchedule, initial_mu, tls_weights

log = logging.getLogger(__name__)

# Hypotheses that move every closure pose by less are one frame: a true group that the robot's
# drift split (the edge-level agreement tolerates 1 m plus 5 % of the lever arm, so over a long
# path drift can exceed it) differs by well under this. Two copies of one room differ by at least
# a room's width, and a hypothesis that merges an alias closer than this with the truth is still
# checked against the maps, and its edges start at weight 0 unless they fit the adopted frame
# on their own (:data:`KEEP_M`).
SAME_FRAME_M = 2.5
KEEP_M = 1.0  # an adopted frame rests on the unmerged groups that it moves by less than this


@dataclass
class Alignment:
    """``T`` maps own-frame poses into the team frame; ``inliers`` flags the measurements used."""

    T: np.ndarray
    inliers: np.ndarray
    ok: bool


def project_so3(M: np.ndarray) -> np.ndarray:
    """Closest rotation (Frobenius) to a 3x3 matrix."""
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def chordal_threshold(angle: float) -> float:
    """Squared chordal distance ``‖R₁ − R₂‖²_F`` of two rotations ``angle`` apart."""
    return 8.0 * np.sin(angle / 2.0) ** 2


def predicted_neighbours(own: np.ndarray, measurement: np.ndarray,
                         own_is_i: np.ndarray) -> np.ndarray:
    """Neighbour poses predicted in the own frame: ``X_own Z`` or ``X_own Z⁻¹``."""
    Z = np.where(np.asarray(own_is_i)[:, None, None], measurement, inverse(measurement))
    return own @ Z


def gnc_rotation_average(rotations: np.ndarray, barc2: float,
                         max_iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Robust chordal mean of rotations ``(k, 3, 3)``: ``(R, weights)``."""
    w = np.ones(len(rotations))
    R = project_so3(rotations.sum(0))
    r2 = np.sum((rotations - R) ** 2, axis=(1, 2))
    mu = initial_mu(float(r2.max()), barc2)
    for _ in range(max_iterations):
        w = tls_weights(r2, mu, barc2)
        if w.sum() <= 0:
            break
        R = project_so3(np.einsum("k,kij->ij", w, rotations))
        r2 = np.sum((rotations - R) ** 2, axis=(1, 2))
        if GncSchedule.binary(w):
            break
        mu *= MU_STEP
    return R, w


def gnc_translation_average(t: np.ndarray, barc2: float,
                            max_iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Robust mean of translations ``(k, 3)``: ``(t, weights)``."""
    w = np.ones(len(t))
    mean = np.median(t, axis=0)
    r2 = np.sum((t - mean) ** 2, axis=1)
    mu = initial_mu(float(r2.max()), barc2)
    for _ in range(max_iterations):
        w = tls_weights(r2, mu, barc2)
        if w.sum() <= 0:
            break
        mean = (w[:, None] * t).sum(0) / w.sum()
        r2 = np.sum((t - mean) ** 2, axis=1)
        if GncSchedule.binary(w):
            break
        mu *= MU_STEP
    return mean, w


def align_frames(own: np.ndarray, neighbour: np.ndarray, measurement: np.ndarray,
                 own_is_i: np.ndarray, rotation_threshold: float = 0.5,
                 translation_threshold: float | None = None, min_inliers: int = 3) -> Alignment:
    """Align the own frame to the team frame from ``k`` inter-robot measurements.

    ``own`` are own poses (own frame), ``neighbour`` the other ends (team frame), ``measurement``
    the relative poses ``Xᵢ⁻¹Xⱼ`` and ``own_is_i`` whether the own pose is the edge's ``i``.
    ``translation_threshold`` defaults to the larger of 5 robust standard deviations of the
    candidates and a tenth of their lever arm (rotation error moves far poses further).
    """
    k = len(own)
    if k == 0:
        return Alignment(np.eye(4), np.zeros(0, dtype=bool), False)
    P = predicted_neighbours(own, measurement, own_is_i)
    rot = neighbour[:, :3, :3] @ np.swapaxes(P[:, :3, :3], 1, 2)
    R, w_rot = gnc_rotation_average(rot, chordal_threshold(rotation_threshold))
    rot_in = w_rot > 0.5
    t_all = neighbour[:, :3, 3] - P[:, :3, 3] @ R.T
    inliers = rot_in.copy()
    t = np.zeros(3)
    if rot_in.any():
        t_in = t_all[rot_in]
        if translation_threshold is None:
            # noise plus the lever arm of a few degrees of rotation drift
            dev = np.linalg.norm(t_in - np.median(t_in, axis=0), axis=1)
            lever = np.linalg.norm(P[rot_in, :3, 3] - P[rot_in, :3, 3].mean(0), axis=1)
            translation_threshold = max(5.0 * 1.4826 * float(np.median(dev)),
                                        0.1 * (1.0 + float(np.median(lever))), 1e-6)
        t, w_t = gnc_translation_average(t_in, translation_threshold**2)
        inliers[np.flatnonzero(rot_in)] = w_t > 0.5
        if inliers.any():
            t = t_all[inliers].mean(0)
    ok = int(inliers.sum()) >= min_inliers
    if not ok:
        log.info("alignment found %d of %d consistent measurements (< %d)",
                 int(inliers.sum()), k, min_inliers)
    return Alignment(make_pose(R, t), inliers, ok)


def agreement(own: np.ndarray, neighbour: np.ndarray, measurement: np.ndarray, own_is_i: np.ndarray,
              rotation_threshold: float = 0.5, translation_tolerance: float = 1.0,
              lever_ratio: float = 0.1) -> np.ndarray:
    """``(k, k)`` symmetric mask: edges ``e`` and ``f`` propose the same frame transform.

    Edge ``e`` proposes ``T_e`` (team ← own frame). ``f`` agrees when ``T_e`` predicts ``f``'s
    neighbour pose within ``rotation_threshold`` (rad) and ``translation_tolerance`` plus
    ``lever_ratio`` times the distance between the two own poses (rotation error and drift grow
    with it), or the other way round. The diagonal is False.
    """
    P = predicted_neighbours(own, measurement, own_is_i)
    T = neighbour @ inverse(P)
    R, t = T[:, :3, :3], T[:, :3, 3]
    pt = P[:, :3, 3]
    # rotation: ‖R_e − R_f‖²_F = 6 − 2 tr(R_eᵀ R_f)
    d_rot = 6.0 - 2.0 * np.einsum("eij,fij->ef", R, R)
    # translation: T_e applied to f's prediction against f's neighbour
    pred = np.einsum("eij,fj->efi", R, pt) + t[:, None, :]
    d_t = np.linalg.norm(pred - neighbour[None, :, :3, 3], axis=2)
    lever = np.linalg.norm(own[:, None, :3, 3] - own[None, :, :3, 3], axis=2)
    ok = (d_rot <= chordal_threshold(rotation_threshold)) & (
        d_t <= translation_tolerance + lever_ratio * lever)
    ok = ok | ok.T
    np.fill_diagonal(ok, False)
    return np.asarray(ok)


def supported_edges(own: np.ndarray, neighbour: np.ndarray, measurement: np.ndarray,
                    own_is_i: np.ndarray, rotation_threshold: float = 0.5,
                    translation_tolerance: float = 1.0, lever_ratio: float = 0.1,
                    min_support: int = 1) -> np.ndarray:
    """Inter-robot edges whose frame hypothesis at least ``min_support`` other edges share
    (see :func:`agreement`).

    Unlike :func:`align_frames` this keeps *every* consistent group, not only the largest:
    aliased closures (identical places) come in mutually consistent groups that can outnumber
    the true group for one robot pair. An unsupported edge agrees with no other: a random outlier.
    """
    if len(own) == 0:
        return np.zeros(0, dtype=bool)
    ok = agreement(own, neighbour, measurement, own_is_i, rotation_threshold, translation_tolerance, lever_ratio)
    return np.asarray(ok.sum(1) >= min_support)


@dataclass
class FrameHypothesis:
    """One candidate frame transform and the evidence for it.

    ``edges`` index the measurements it explains; ``places`` is its support: the number of
    distinct places (per neighbour robot, own poses closer than ``place_radius`` chained into
    one place) those measurements come from. An aliased group (two identical rooms) is one
    place; the true frame explains closures wherever the robots' paths really overlap.
    """

    T: np.ndarray
    edges: np.ndarray
    places: int
    peers: tuple[int, ...]
    xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # own position of each edge
    edge_peers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))  # peer of each edge

    @property
    def size(self) -> int:
        return len(self.edges)


def _hypothesis(T: np.ndarray, edges: np.ndarray, own: np.ndarray, peers: np.ndarray,
                place_radius: float) -> FrameHypothesis:
    """The hypothesis of ``edges`` (indices into ``own``/``peers``), its places counted per peer."""
    xyz, by = own[edges, :3, 3], peers[edges]
    places = sum(count_places(xyz[by == p], place_radius) for p in np.unique(by))
    return FrameHypothesis(T, edges, int(places), tuple(int(p) for p in np.unique(by)), xyz, by)


def exclusive_places(a: FrameHypothesis, b: FrameHypothesis, radius: float) -> int:
    """Places of ``a`` that ``b`` does not explain: per peer, ``a``'s closure positions farther
    than ``radius`` from every closure position ``b`` has with that peer, counted as places.

    Identical rooms make an alias explain closures only where the truth has them too (a row of
    twin rooms shifted by one: every aliased closure sits in a room the robot really met its peer
    in), while the true frame alone explains the places that look like no other.
    """
    count = 0
    for p in np.unique(a.edge_peers):
        pa, pb = a.xyz[a.edge_peers == p], b.xyz[b.edge_peers == p]
        if len(pb):
            d = np.linalg.norm(pa[:, None] - pb[None], axis=2).min(1)
            pa = pa[d > radius]
        count += count_places(pa, radius)
    return count


def count_places(points: np.ndarray, radius: float) -> int:
    """Connected components of ``points (n, 3)`` under single linkage at ``radius``."""
    if len(points) == 0:
        return 0
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    n, _ = connected_components(csr_matrix(d <= radius), directed=False)
    return int(n)


def frame_hypotheses(own: np.ndarray, neighbour: np.ndarray, measurement: np.ndarray, own_is_i: np.ndarray,
                     peers: np.ndarray, rotation_threshold: float = 0.2, translation_tolerance: float = 1.0,
                     lever_ratio: float = 0.05, place_radius: float = 2.0, min_edges: int = 2,
                     max_hypotheses: int = 8, merge_distance: float = SAME_FRAME_M) -> list[FrameHypothesis]:
    """The distinct frame hypotheses the measurements propose, best supported first.

    Greedy clustering of :func:`agreement`: the edge most others agree with seeds a group, the
    group's transform is re-estimated robustly (:func:`align_frames`) and its inliers leave the
    pool; repeat. Hypotheses that move the robot's closure poses by less than ``merge_distance``
    are one (drift splits a true group; identical rooms sit further apart). Ranked by
    ``places``, then by size. Every neighbour's measurements vote in the
    same (team) frame, so the true hypothesis gathers support across robots and places, while
    each aliased one is confined to the places that look alike.
    """
    k = len(own)
    out: list[FrameHypothesis] = []
    if k == 0:
        return out
    peers = np.asarray(peers)
    ok = agreement(own, neighbour, measurement, own_is_i, rotation_threshold, translation_tolerance, lever_ratio)
    left = np.ones(k, dtype=bool)
    while left.sum() >= min_edges and len(out) < max_hypotheses:
        score = (ok & left[None, :]).sum(1) * left
        seed = int(np.argmax(score))
        group = np.flatnonzero(left & (ok[seed] | (np.arange(k) == seed)))
        if len(group) < min_edges:
            break
        res = align_frames(own[group], neighbour[group], measurement[group], own_is_i[group],
                           rotation_threshold=rotation_threshold, min_inliers=min_edges)
        members = group[res.inliers] if res.inliers.sum() >= min_edges else group
        T = res.T if res.inliers.sum() >= min_edges else align_frames(
            own[group], neighbour[group], measurement[group], own_is_i[group], min_inliers=1).T
        left[members] = False
        left[seed] = False
        out.append(_hypothesis(T, members, own, peers, place_radius))
    out = _merge_close(out, own, peers, merge_distance, place_radius)
    out.sort(key=lambda h: (-h.places, -h.size))
    return out


def frames_agree(a: FrameHypothesis, b: FrameHypothesis, distance: float) -> bool:
    """Whether ``a`` and ``b`` are one frame: ``a.T⁻¹ b.T`` moves every closure position of either
    by at most ``distance``."""
    pts = np.concatenate([a.xyz, b.xyz])
    if not len(pts):
        return False
    D = inverse(a.T) @ b.T
    return bool(np.linalg.norm(pts @ D[:3, :3].T + D[:3, 3] - pts, axis=1).max() <= distance)


def _merge_close(hyps: list[FrameHypothesis], own: np.ndarray, peers: np.ndarray, distance: float,
                 place_radius: float) -> list[FrameHypothesis]:
    """Join hypotheses whose transforms move the robot's closure poses by less than ``distance``
    (a true group that drift over long lever arms split; aliases sit a room apart)."""
    hyps = list(hyps)
    merged = True
    while merged and len(hyps) > 1:
        merged = False
        for a in range(len(hyps)):
            for b in range(a + 1, len(hyps)):
                ha, hb = hyps[a], hyps[b]
                if not frames_agree(ha, hb, distance):
                    continue
                big = ha if ha.size >= hb.size else hb
                hyps[a] = _hypothesis(big.T, np.concatenate([ha.edges, hb.edges]), own, peers, place_radius)
                del hyps[b]
                merged = True
                break
            if merged:
                break
    return hyps


def decide(hypotheses: list[FrameHypothesis], min_places: int = 2, min_margin: int = 1,
           min_edges: int = 3, lead_ratio: float = 2.0,
           place_radius: float = 2.0) -> tuple[FrameHypothesis | None, int]:
    """The hypothesis that clearly leads, or None; and its margin in places over the runner-up.

    A frame resting on a single place (one group, which an alias would look like) or tied with
    another hypothesis is not decided: the robot waits for more evidence (or stays out of the
    team frame). A hypothesis leads a competitor that rests on fewer than two places by
    ``min_margin`` places. A competitor resting on several places is a twin room with several
    distinct spots (a twin room's desks are several places): then the leader needs
    ``lead_ratio`` times its places (a lead of one place over a twin room is within what one
    more visit to either room changes), or ``lead_ratio`` times the places only the competitor
    explains (:func:`exclusive_places`), and at least ``min_places`` of its own. The latter tells
    a row of identical rooms from the truth: the frame shifted by one room explains closures in
    every room of the row but one, so it can rest on nearly as many places as the truth, yet it
    explains few places the true frame does not, while the truth alone explains every place that
    looks like no other. The margin of a
    decided hypothesis is its smallest lead over a competitor, in places or in exclusive places,
    whichever decided it.
    """
    if not hypotheses:
        return None, 0
    places_margin = hypotheses[0].places - (hypotheses[1].places if len(hypotheses) > 1 else 0)
    for best in hypotheses:
        if best.places < min_places or best.size < min_edges:
            continue
        margin: int | None = None
        for h in hypotheses:
            if h is best:
                continue
            lead = best.places - h.places
            need = min_margin if h.places < 2 else max(min_margin, int(np.ceil((lead_ratio - 1.0) * h.places)))
            if lead < need:
                own, other = exclusive_places(best, h, place_radius), exclusive_places(h, best, place_radius)
                if own < max(min_places, other + min_margin, lead_ratio * other):
                    break
                lead = own - other
            margin = lead if margin is None else min(margin, lead)
        else:
            return best, best.places if margin is None else margin
    return None, places_margin


def same_frame(a: FrameHypothesis, b: FrameHypothesis) -> bool:
    """One frame: the two share at least half of the smaller one's edges, or (disjoint edges, as
    through two peers) their transforms move every closure pose of either by less than a room."""
    if len(np.intersect1d(a.edges, b.edges)) * 2 >= min(len(a.edges), len(b.edges)):
        return True
    return frames_agree(a, b, SAME_FRAME_M)


def unrefuted_rivals(best: FrameHypothesis, hyps: Sequence[FrameHypothesis],
                     refuted: Sequence[bool] = (), min_places: int = 2) -> list[FrameHypothesis]:
    """The hypotheses of ``hyps`` that are another frame than ``best``, rest on ``min_places``
    places or more, and that nothing refuted.

    ``hyps`` are what the maps left (a hypothesis the maps refute is dropped before the decision);
    ``refuted`` flags, aligned with ``hyps``, those other evidence refuted (the team's object
    landmarks). With the team map on, a robot adopts a frame only when this is empty: a frame that
    leads on closures alone is no proof while a rival of several places stands that the maps
    cannot tell from it (docs/algorithms/pgo.md, "Every rival refuted"). A rival on fewer places
    is what one twin room looks like, and the closures already refute it: the adopted frame
    rests on more distinct places than it (:func:`decide`), and the maps and the safety net
    judge the frame afterwards.
    """
    return [h for i, h in enumerate(hyps)
            if h is not best and h.places >= min_places and not (i < len(refuted) and refuted[i])
            and not same_frame(h, best)]


def near_identity(T: np.ndarray, max_trans: float = 1.0, max_rot: float = 0.2) -> bool:
    """A frame hypothesis that is (within alignment tolerance) no change of frame."""
    return bool(np.linalg.norm(T[:3, 3]) <= max_trans and np.linalg.norm(so3_log(T[None, :3, :3])[0]) <= max_rot)


def settled_decision(firm: list[FrameHypothesis] | None, every: list[FrameHypothesis],
                     per_peer: Sequence[list[FrameHypothesis]] = (), min_places: int = 2,
                     min_margin: int = 1, place_radius: float = 2.0) -> tuple[FrameHypothesis | None, int, str]:
    """Decide a frame on settled peers' edges (``firm``; None when every edge is one, empty when
    none is) and on
    every known edge (``every``); ``per_peer``: each settled peer's hypotheses on its own edges.
    Returns the hypothesis (or None), its margin and a verdict:

    * ``"settled"``: settled peers' evidence decides, every edge does not decide another frame
      (the larger hypothesis when both agree), and no settled peer's own edges clearly lead to
      another frame (frames through different peers must agree: A–B ∘ B–C ≈ A–C);
    * ``"contested"``: two of these decide different frames, and nothing is decided. A robot in
      an alias carries the robots that met it into the alias, and one peer's twin rooms can
      outvote another peer's true places; neither is evidence against the other;
    * ``"unsettled"``: only every edge decides (or nothing does).
    """
    def decided(hyps: list[FrameHypothesis]) -> tuple[FrameHypothesis | None, int]:
        return decide(hyps, min_places, min_margin, place_radius=place_radius)

    best, margin = decided(every)
    verdict = "settled" if best is not None else "unsettled"
    if firm is not None:
        lead, lead_margin = decided(firm)
        if lead is None:
            verdict = "unsettled"
        elif best is None:
            best, margin, verdict = lead, lead_margin, "settled"
        elif not same_frame(lead, best):
            return None, 0, "contested"
    leads = [h for h in (decided(hyps)[0] for hyps in per_peer) if h is not None]
    ref = best if best is not None else (leads[0] if leads else None)
    if ref is not None and any(not same_frame(h, ref) for h in leads):
        return None, 0, "contested"
    return best, margin, verdict


def drift_sigmas(odometry_xyz: np.ndarray, sigma_rot: float, sigma_trans: float) -> np.ndarray:
    """Per-keyframe position standard deviation of dead reckoning ``(n,)`` (m).

    A random walk per keyframe of ``sigma_trans`` (m, per axis) plus the lever arm of the
    accumulated heading error: a rotation error ``δθ_m`` at keyframe ``m`` moves keyframe ``k``
    by ``|p_k − p_m| δθ_m``, so ``σ_k² = k σ_t² + 2 σ_r² Σ_{m<k} |p_k − p_m|²``. The real path's
    geometry bounds the lever arm (a robot touring a floor stays within it), which the
    straight-line ``L³/3`` bound does not.
    """
    p = np.asarray(odometry_xyz, dtype=float)
    n = len(p)
    k = np.arange(n)
    S = np.vstack([np.zeros(3), np.cumsum(p, axis=0)[:-1]]) if n else np.zeros((0, 3))
    Q = np.concatenate([[0.0], np.cumsum((p**2).sum(1))[:-1]]) if n else np.zeros(0)
    lever2 = np.maximum(k * (p**2).sum(1) - 2.0 * (p * S).sum(1) + Q, 0.0)
    return np.asarray(np.sqrt(k * sigma_trans**2 + 2.0 * sigma_rot**2 * lever2))


def odometry_disagreement(poses: np.ndarray, odometry: np.ndarray, sigma_rot: float, sigma_trans: float,
                          z: float = 4.0, floor: float = 0.5) -> float:
    """How far an estimate bends away from the robot's own dead reckoning, in units of its drift
    model: ``max_k |dev_k| / (z·σ_max + floor)`` after one rigid alignment of the estimate onto
    the odometry (the frame does not matter, the shape does). Above 1: the estimate disagrees
    with the robot's odometry beyond what drift explains (false closures bent it)."""
    from kimera_multi_py.core.geometry import umeyama

    P, D = np.asarray(poses)[:, :3, 3], np.asarray(odometry)[:, :3, 3]
    if len(P) < 3:
        return 0.0
    R, t, _ = umeyama(P, D)
    dev = np.linalg.norm(P @ R.T + t - D, axis=1)
    sigma = float(drift_sigmas(D, sigma_rot, sigma_trans).max())
    return float(dev.max() / (z * sigma + floor))
