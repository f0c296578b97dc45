import numpy as np
import pytest

from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp, transform_points
from kimera_multi_py.mapping import SemanticOctree, SubmapMap

from .helpers import HUMAN, TABLE, WALL, K, room_scan

RES = 0.1
SENSORS = [
    np.array(p)
    for p in (
        [0.0, 0.0, 1.0],
        [-1.5, 1.0, 1.2],
        [1.0, -1.2, 0.9],
        [-2.0, -1.5, 1.5],
        [0.5, 1.5, 1.1],
        [2.0, 1.0, 1.3],
    )
]


def submap_poses():
    return {
        0: make_pose(so3_exp([0, 0, 0.3]), [0.2, -0.1, 0.0]),
        1: make_pose(so3_exp([0, 0, -1.1]), [-1.0, 0.5, 0.1]),
        2: make_pose(None, [1.5, 0.0, 0.0]),
    }


def build(skip=(), seed=0, moved=None, offset=(0.0, 0.0, 0.0), **kw):
    """Three submaps of two scans each; scans are given in each keyframe's sensor frame.

    ``moved`` maps a submap id to a world transform: that submap is created there instead (its
    scans keep their pose in the submap, so they are integrated at the moved pose). ``offset``
    moves every sensor origin (the default ones lie on voxel faces, where a ray cast from a
    shifted origin may start one voxel over through rounding).
    """
    m = SubmapMap(RES, K, dynamic_classes=[HUMAN], **kw)
    moved = moved or {}
    for sid, T_ws in submap_poses().items():
        if sid in skip:
            continue
        m.new_submap(sid, moved.get(sid, np.eye(4)) @ T_ws)
        for j in range(2):
            o = SENSORS[2 * sid + j] + np.asarray(offset)
            p, lab = room_scan(o, 3000, seed=seed + 10 * sid + j, noise=0.1)
            T_w_sensor = make_pose(so3_exp([0.1 * j, 0, 0.5 * sid]), o)
            T_s_sensor = inverse(T_ws) @ T_w_sensor
            m.integrate(sid, T_s_sensor, transform_points(inverse(T_w_sensor), p), lab)
    return m


def snapshot(tree: SemanticOctree):
    return tree.codes.copy(), tree.levels.copy(), tree.values.copy()


def same(a, b):
    return all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_the_fused_map_agrees_with_direct_insertion():
    m = build()
    direct = SemanticOctree(RES, K, dynamic_classes=[HUMAN])
    for sid in (0, 1, 2):
        for j in range(2):
            o = SENSORS[2 * sid + j]
            direct.insert_scan(o, *room_scan(o, 3000, seed=10 * sid + j, noise=0.1))
    probes = np.array([[-3.05, 0.33, 1.31], [0.0, 0.5, 1.5], [9.0, 0, 0]])
    assert np.array_equal(m.octree.class_at(probes), [WALL, 0, -1])
    centers = direct.leaves().centers
    agree = m.octree.class_at(centers) == direct.class_at(centers)
    assert agree.mean() > 0.97
    occ = direct.occupied_leaves()
    assert (m.octree.class_at(centers[occ]) == direct.class_at(centers[occ])).mean() > 0.9
    assert np.any(m.octree.class_at(centers) == TABLE)


def test_moving_a_submap_away_and_back_restores_the_map_bit_for_bit():
    m = build()
    before = snapshot(m.octree)
    evidence = m.evidence()
    T1 = m.submaps[1].T.copy()
    away = make_pose(so3_exp([0.02, -0.01, 0.25]), [0.7, -0.4, 0.05]) @ T1
    assert m.move_submap(1, away)
    moved = snapshot(m.octree)
    assert not same(before, moved)
    assert m.move_submap(2, make_pose(None, [0.0, 0.35, 0.0]) @ m.submaps[2].T)
    assert m.move_submap(1, T1)
    assert m.move_submap(2, submap_poses()[2])
    assert same(before, snapshot(m.octree))
    assert same(evidence, m.evidence())


def test_moving_by_whole_voxels_equals_integrating_there():
    shift = make_pose(None, [0.3, -0.2, 0.1])
    mid = (0.05, 0.05, 0.05)  # sensor origins at voxel centres
    m = build(offset=mid)
    assert m.move_submap(0, shift @ m.submaps[0].T)
    # independently: a fresh map whose submap 0 is created at the shifted pose, its scans
    # ray-cast there from scratch
    ref = build(moved={0: shift}, offset=mid)
    assert same(snapshot(ref.octree), snapshot(m.octree))
    assert same(ref.evidence(), m.evidence())
    assert not same(snapshot(build(offset=mid).octree), snapshot(m.octree))


def test_removing_a_submap_equals_never_adding_it():
    m = build()
    m.remove_submap(1)
    assert same(snapshot(m.octree), snapshot(build(skip=(1,)).octree))
    assert 1 not in m.submap_ids()


def test_small_corrections_wait_for_the_threshold():
    m = build()
    before = snapshot(m.octree)
    T = m.submaps[2].T.copy()
    assert not m.move_submap(2, make_pose(None, [0.02, 0.0, 0.0]) @ T)
    assert same(before, snapshot(m.octree))
    assert m.move_submap(2, make_pose(None, [0.02, 0.0, 0.0]) @ T, force=True)
    assert not m.move_submap(2, make_pose(None, [0.03, 0.0, 0.0]) @ T)  # 1 cm from applied
    assert m.move_submap(2, make_pose(None, [0.2, 0.0, 0.0]) @ T)


def test_submap_ids_are_checked():
    m = SubmapMap(RES, K)
    m.new_submap(3, np.eye(4))
    with pytest.raises(KeyError):
        m.new_submap(3, np.eye(4))
    with pytest.raises(KeyError):
        m.integrate(4, np.eye(4), np.ones((1, 3)), np.array([1]))
    assert m.integrate(3, np.eye(4), np.zeros((0, 3)), np.zeros(0, int)) == 0


def _rebuilt(m: SubmapMap):
    """The map's tree built anew from its evidence, in one batch."""
    codes, rows, _ = m.evidence()
    tree = m.template.empty_like()
    vals = rows + tree.model.prior_row.astype(np.int32)
    np.clip(vals, tree.model.lo, tree.model.hi, out=vals)
    vals[:, 0] = 0
    tree.set_cells(codes, vals.astype(np.int16))
    return tree


def test_the_tree_read_between_updates_equals_the_tree_rebuilt_from_the_evidence():
    """The tree is brought up to date only when read: read after every update, after some, or
    only at the end, it holds the same leaves as a tree built from the evidence at that moment."""
    every, rarely = build(), build()
    assert same(snapshot(every.octree), snapshot(rarely.octree))
    rng = np.random.default_rng(3)
    for step in range(12):
        sid = int(rng.choice(every.submap_ids()))
        pose = make_pose(so3_exp(rng.normal(0, 0.05, 3)), rng.normal(0, 0.3, 3)) @ submap_poses()[sid]
        for m in (every, rarely):
            m.move_submap(sid, pose)
        if step == 7:
            for m in (every, rarely):
                m.remove_submap(2)
        assert same(snapshot(every.octree), snapshot(_rebuilt(every)))
    assert same(snapshot(rarely.octree), snapshot(every.octree))
    assert len(rarely.octree) > 0 and not rarely._pending


def test_the_changed_cells_kept_for_the_tree_stay_bounded():
    m = build()
    m.octree  # noqa: B018  (brings the tree up to date)
    T = m.submaps[0].T.copy()
    for i in range(300):  # re-anchor the same submap back and forth without reading the tree
        m.move_submap(0, make_pose(None, [0.3 * (i % 2), 0.0, 0.0]) @ T)
    kept = sum(len(p) for p in m._pending)
    assert len(m._pending) < 65 and kept <= 64 * 2 * len(m.submaps[0].codes)
    assert same(snapshot(m.octree), snapshot(_rebuilt(m)))


def test_group_sums_equal_a_dictionary_sum_on_runs_of_sorted_codes() -> None:
    """Sums and multiplicities per code against a plain dictionary sum, on what the fusions feed
    it: concatenated runs of sorted codes that overlap, shuffled codes, and no codes."""
    from kimera_multi_py.mapping.palette import to_palette
    from kimera_multi_py.mapping.submaps import _group_sum, group_sum_indexed, group_sums

    rng = np.random.default_rng(0)
    runs = [np.sort(rng.choice(5000, size=800, replace=False)) for _ in range(6)]
    for codes in (np.concatenate(runs), rng.permutation(np.concatenate(runs)), np.zeros(0, np.int64)):
        rows = rng.integers(-300, 300, size=(len(codes), 4)).astype(np.int16)
        uniq, summed, count = _group_sum(codes, rows)
        want: dict[int, np.ndarray] = {}
        for c, r in zip(codes.tolist(), rows.astype(np.int64), strict=True):
            want[c] = want.get(c, 0) + r
        assert uniq.tolist() == sorted(want)
        assert all(np.array_equal(summed[i], want[c]) for i, c in enumerate(uniq.tolist()))
        assert count.sum() == len(codes) and np.array_equal(count, [np.sum(codes == c) for c in uniq])
        u2, (s2,) = group_sums(codes, rows)
        assert np.array_equal(u2, uniq) and np.array_equal(s2, summed)
        palette, index = to_palette(rows)  # the same rows as a palette and indices
        u3, s3 = group_sum_indexed(codes, palette, index)
        assert np.array_equal(u3, uniq) and np.array_equal(s3, summed) and s3.dtype == palette.dtype


def test_closed_submaps_hold_their_rows_compactly_with_the_same_values(monkeypatch):
    """Submaps that take no more scans keep their rows as a palette and no world codes: fewer
    bytes, and the same rows, contributions and map, through moves and a late scan into one,
    as a map that keeps every submap dense."""
    m = build()
    assert [m.submaps[s].compact_rows for s in (0, 1, 2)] == [True, True, False]
    monkeypatch.setattr("kimera_multi_py.mapping.submaps.Submap.compact", lambda self: None)
    dense = build()
    assert not any(s.compact_rows for s in dense.submaps.values())
    for sid in (0, 1):
        s, d = m.submaps[sid], dense.submaps[sid]
        assert s.world_codes is None and s.nbytes < d.nbytes / 2
        assert np.array_equal(s.rows, d.rows)
        assert all(np.array_equal(a, b) for a, b in zip(m.contribution(sid), dense.contribution(sid), strict=True))

    def change(x: SubmapMap) -> None:
        x.move_submap(0, make_pose(so3_exp([0.0, 0.01, -0.2]), [0.4, 0.3, 0.0]) @ x.submaps[0].T)
        o = SENSORS[1]
        p, lab = room_scan(o, 2000, seed=99, noise=0.1)
        T_w_sensor = make_pose(None, o)
        x.integrate(1, inverse(x.submaps[1].T_ref) @ T_w_sensor, transform_points(inverse(T_w_sensor), p), lab)
        x.move_submap(1, make_pose(None, [0.0, -0.3, 0.0]) @ x.submaps[1].T)

    change(m)
    change(dense)
    assert not m.submaps[1].compact_rows  # the late scan expanded it
    assert same(snapshot(m.octree), snapshot(dense.octree))
    assert same(m.evidence(), dense.evidence())
    for sid in (0, 1, 2):
        assert np.array_equal(m.submaps[sid].rows, dense.submaps[sid].rows)
