"""Robust frame alignment between two robots from their inter-robot measurements.

Each measurement between an own pose (own frame) and a neighbour pose (team frame) proposes one
frame transform ``T_team_own``. GNC-TLS rotation averaging (chordal) picks the rotation and the
rotation inliers; translation averaging (GNC-TLS again) over those inliers gives the
translation. At least ``min_inliers`` consistent measurements are needed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from kimera_multi_py.consensus.robust import MU_STEP, GncSchedule, initial_mu, tls_weights
from kimera_multi_py.geometry import inverse, make_pose

log = logging.getLogger(__name__)


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


def supported_edges(own: np.ndarray, neighbour: np.ndarray, measurement: np.ndarray,
                    own_is_i: np.ndarray, rotation_threshold: float = 0.5,
                    translation_tolerance: float = 1.0, lever_ratio: float = 0.1,
                    min_support: int = 1) -> np.ndarray:
    """Inter-robot edges whose frame hypothesis at least ``min_support`` other edges share.

    Edge ``e`` proposes ``T_e`` (team ← own frame). Edge ``f`` supports it when ``T_e`` predicts
    ``f``'s neighbour pose within ``rotation_threshold`` (rad) and ``translation_tolerance`` plus
    ``lever_ratio`` times the distance between the two own poses (rotation error and drift
    grow with it), or the other way round. Unlike :func:`align_frames` this keeps *every*
    consistent group, not only the largest: aliased closures (identical places) come in
    mutually consistent groups that can outnumber the true group for one robot pair, and only
    the joint graph can tell them apart (GNC's job). An unsupported edge agrees with no other:
    a random outlier.
    """
    k = len(own)
    if k == 0:
        return np.zeros(0, dtype=bool)
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
    return np.asarray(ok.sum(1) >= min_support)
