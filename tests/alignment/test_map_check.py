"""Occupancy agreement: the true frame agrees, a frame one room off is refuted, disjoint maps say nothing."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.alignment.map_check import (
    FREE,
    OCCUPIED,
    cell_states,
    map_agreement,
    occupancy_logodds,
    occupancy_states,
)
from kimera_multi_py.core.geometry import make_pose, so3_exp
from kimera_multi_py.mapping import morton
from kimera_multi_py.mapping.semantic_octree import SCALE
from kimera_multi_py.pgo.params import PgoParams

from .world import Floor, seen

ROOM = 4.0
P = PgoParams()
LIMITS = (P.map_min_conflicts, P.map_conflict_ratio)
# a corridor along y in [4, 6] with a dead end at x = 0, three identical rooms south of it
# (one desk each, in the same place), and a hall east of the row
ROW = Floor(spaces=[(0.0, 4.0, 16.0, 6.0), *[(ROOM * k + 0.1, 0.0, ROOM * (k + 1) - 0.1, 4.0) for k in range(3)],
                    *[(ROOM * k + 1.5, 3.8, ROOM * k + 2.5, 4.2) for k in range(3)], (12.0, 0.0, 16.0, 6.0)],
            boxes=[(ROOM * k + 0.5, 0.5, ROOM * k + 1.5, 1.2) for k in range(3)])


def _path(x0: float, x1: float) -> np.ndarray:
    xs = np.arange(x0, x1, 0.5)
    corridor = np.column_stack([xs, np.full(len(xs), 5.0)])
    rooms = np.array([[ROOM * k + 2.0, 2.0] for k in range(3) if x0 <= ROOM * k + 2.0 < x1]).reshape(-1, 2)
    return np.vstack([corridor, rooms])


def shift(dx: float, dy: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    return make_pose(so3_exp(np.array([0.0, 0.0, yaw])), np.array([dx, dy, 0.0]))


def test_true_frame_agrees_within_residual_misalignment() -> None:
    a = seen(ROW, _path(0.5, 9.0))
    b = seen(ROW, _path(3.0, 15.0), T_world_own=shift(0.04, -0.03, 0.004))  # b's own frame, a few cm off
    ag = map_agreement(a, b, np.linalg.inv(shift(0.04, -0.03, 0.004)))
    assert ag.overlap > 1000
    assert not ag.refutes(*LIMITS) and ag.ratio < P.map_conflict_ratio


def test_a_frame_one_room_off_is_refuted() -> None:
    a = seen(ROW, _path(0.5, 9.0))
    b = seen(ROW, _path(1.0, 15.0))  # both saw the dead end of the corridor
    for dx in (ROOM, -ROOM, 2 * ROOM):
        ag = map_agreement(a, b, shift(dx))
        assert ag.refutes(*LIMITS), (dx, ag)


def test_maps_that_do_not_overlap_neither_agree_nor_refute() -> None:
    a = seen(ROW, _path(0.5, 3.0), radius=1.5)
    b = seen(ROW, _path(13.0, 15.5), radius=1.5)
    ag = map_agreement(a, b, None)
    assert ag.overlap == 0 and ag.ratio == 0.0 and not ag.refutes(*LIMITS)


def test_cell_states_follow_the_occupancy_logodds() -> None:
    # three classes; free pivot 0: strongly occupied, strongly free, and undecided cells
    values = np.array([[0, 3 * SCALE, -4 * SCALE, -4 * SCALE],
                       [0, -3 * SCALE, -3 * SCALE, -3 * SCALE],
                       [0, 0, -5 * SCALE, -5 * SCALE]], dtype=np.int16)
    codes = morton.points_to_codes(np.array([[0.05, 0.05, 0.05], [1.05, 0.05, 0.05], [2.05, 0.05, 0.05]]), 0.1)
    st = cell_states(codes, values, 0.1, threshold=1.0)
    assert st.state.tolist() == [1, -1]
    assert np.allclose(st.centres[:, 0], [0.05, 1.05])


def test_a_frame_near_the_truth_is_refined_even_when_gicp_stops_at_its_cap(monkeypatch) -> None:
    """A hypothesis a few decimetres off (closures at one place, seen from far away) is refined
    by registration; that GICP stops at its iteration cap without reporting convergence (which
    varies between builds) must not leave the true frame refuted. One room off stays refuted."""
    from kimera_multi_py.alignment import map_check
    from kimera_multi_py.mapping.registration import ScanRegistration

    monkeypatch.setattr(map_check, "_REGISTRATION",
                        ScanRegistration(voxel=0.2, max_correspondence=(1.0, 0.5, 0.25), max_iterations=1))
    a = seen(ROW, _path(0.5, 9.0))
    b = seen(ROW, _path(1.0, 15.0))  # both saw the dead end of the corridor
    off = make_pose(so3_exp(np.array([0.02, 0.0, -0.1])), np.array([0.6, 0.3, -0.3]))
    assert map_agreement(a, b, off).refutes(*LIMITS)
    refined = map_check.refined_agreement(a, b, off)
    assert not refined.refutes(*LIMITS), refined
    for dx in (ROOM, -ROOM, 2 * ROOM):
        assert map_check.refined_agreement(a, b, shift(dx) @ off).refutes(*LIMITS), dx


def test_cell_states_skip_the_log_sum_exp_only_where_it_cannot_change_the_state() -> None:
    """The states from the largest log-odds bound equal the thresholded log-sum-exp, on random
    rows, strongly free rows and rows whose bound sits exactly at a threshold."""
    rng = np.random.default_rng(0)
    for t in (0.0, 0.5, 1.0, 2.0, -0.5):
        lim = int(5 * SCALE)
        rows = [rng.integers(-lim, lim + 1, size=(2000, 12)), rng.integers(-lim, -lim // 3, size=(2000, 12)),
                np.full((50, 12), -lim), np.full((50, 12), int(t * SCALE)), np.full((50, 12), -int(t * SCALE)),
                np.full((50, 3), int(-(t + np.log(2)) * SCALE))]
        for r in rows:
            v = r.astype(np.int16)
            v[:, 0] = 0
            lo = occupancy_logodds(v)
            want = np.where(lo > t, OCCUPIED, np.where(lo < -t, FREE, np.int8(0)))
            assert np.array_equal(occupancy_states(v, t), want)
