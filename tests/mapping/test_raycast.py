import numpy as np
import pytest

from kimera_multi_py.mapping import morton, raycast
from kimera_multi_py.mapping.raycast import scan_cells

from .helpers import HUMAN, K, aw_traverse, keys_of, sphere_dirs

RES = 0.1


def random_rays(n, seed, origin=(0.37, -1.21, 1.03), max_len=6.0):
    rng = np.random.default_rng(seed)
    o = np.array(origin)
    return o, o + sphere_dirs(n, rng) * rng.uniform(0.05, max_len, n)[:, None]


def reference_free(o, pts, res=RES):
    free = set()
    for p in pts:
        free.update(aw_traverse(o, p, res))
    ends = {tuple(np.floor(p / res).astype(int)) for p in pts}
    return free - ends, ends


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_free_cells_are_the_union_of_per_ray_walks(seed):
    o, pts = random_rays(400, seed)
    cells = scan_cells(o, pts, np.zeros(len(pts), int), RES, K)
    free_ref, _ = reference_free(o, pts)
    ours = keys_of(cells.free)
    # float32 progressions may disagree with the float64 walk only at exact corner crossings
    assert len(ours ^ free_ref) <= 2
    assert len(cells.occupied) == 0  # label 0 = no return: free space only
    assert np.all(np.diff(cells.free) > 0)


def test_hits_mark_end_voxels_with_label_histograms():
    o = np.array([0.05, 0.05, 0.05])
    pts = np.array([[1.01, 0.02, 0.03], [1.04, 0.07, 0.01], [1.03, 0.05, 0.04], [0.05, 2.0, 0.05]])
    lab = np.array([5, 5, 6, 1])
    cells = scan_cells(o, pts, lab, RES, K)
    assert keys_of(cells.occupied) == {(10, 0, 0), (0, 20, 0)}
    row = cells.label_counts[np.flatnonzero(keys_of_list(cells.occupied) == [10, 0, 0])[0]]
    assert row[5] == 2 and row[6] == 1 and row.sum() == 3
    # the origin's voxel and the cells in between are free; end voxels never are
    free = keys_of(cells.free)
    assert (0, 0, 0) in free and (5, 0, 0) in free and (0, 10, 0) in free
    assert not free & keys_of(cells.occupied)


def keys_of_list(codes):
    return morton.decode(codes) - morton.KEY_OFFSET


def test_occupied_wins_over_free():
    o = np.array([0.05, 0.05, 0.05])
    pts = np.array([[2.05, 0.05, 0.05], [1.05, 0.05, 0.05]])  # the second ends on the first's path
    cells = scan_cells(o, pts, np.array([1, 1]), RES, K)
    assert (10, 0, 0) in keys_of(cells.occupied)
    assert (10, 0, 0) not in keys_of(cells.free)
    assert (15, 0, 0) in keys_of(cells.free)


def test_rays_beyond_max_range_only_clear_space():
    o = np.array([0.05, 0.05, 0.05])
    pts = np.array([[5.05, 0.05, 0.05], [0.05, 1.05, 0.05]])
    cells = scan_cells(o, pts, np.array([1, 1]), RES, K, max_range=3.0)
    assert keys_of(cells.occupied) == {(0, 10, 0)}
    free_x = sorted(k[0] for k in keys_of(cells.free) if k[1] == 0)
    assert free_x[-1] == 29  # cut at 3 m: the voxel at the cut is the end, left untouched
    assert (30, 0, 0) not in keys_of(cells.free) and (49, 0, 0) not in keys_of(cells.free)


def test_dynamic_labels_only_clear_space():
    o = np.array([0.05, 0.05, 0.05])
    pts = np.array([[1.05, 0.05, 0.05], [0.05, 1.05, 0.05]])
    cells = scan_cells(o, pts, np.array([HUMAN, 1]), RES, K, dynamic_labels=(HUMAN,))
    assert keys_of(cells.occupied) == {(0, 10, 0)}
    assert (9, 0, 0) in keys_of(cells.free) and (10, 0, 0) not in keys_of(cells.free)


def test_bitmap_and_sort_paths_agree(monkeypatch):
    o, pts = random_rays(2000, 7)
    lab = np.random.default_rng(7).integers(0, K + 1, len(pts))
    a = scan_cells(o, pts, lab, RES, K, max_range=4.0)
    monkeypatch.setattr(raycast, "_DENSE_LIMIT", 0)
    monkeypatch.setattr(raycast, "_BLOCK", 997)  # many small blocks
    b = scan_cells(o, pts, lab, RES, K, max_range=4.0)
    assert np.array_equal(a.free, b.free)
    assert np.array_equal(a.occupied, b.occupied)
    assert np.array_equal(a.label_counts, b.label_counts)


def test_bad_input():
    o = np.zeros(3)
    with pytest.raises(ValueError, match="labels"):
        scan_cells(o, np.ones((2, 3)), np.array([1, K + 1]), RES, K)
    with pytest.raises(ValueError):
        scan_cells(o, np.ones((2, 2)), np.array([1, 1]), RES, K)
    with pytest.raises(ValueError, match="extent"):
        scan_cells(o, np.array([[5000.0, 0, 0]]), np.array([1]), RES, K)
    cells = scan_cells(o, np.array([[np.nan, 0, 0], [0.5, 0, 0]]), np.array([1, 1]), RES, K)
    assert len(cells.occupied) == 1 and cells.num_rays == 1
    empty = scan_cells(o, np.zeros((0, 3)), np.zeros(0, int), RES, K)
    assert empty.num_cells == 0


def test_free_margin_and_surface_offset():
    o = np.array([0.05, 0.05, 0.05])
    pts = np.array([[2.0, 0.05, 0.05], [0.05, 3.05, 0.05]])  # a hit on a voxel boundary (x = 2.0)
    lab = np.array([1, 0])  # the second ray has no return: margin does not apply to it
    plain = scan_cells(o, pts, lab, RES, K)
    assert (20, 0, 0) in keys_of(plain.occupied)  # floor(2.0 / 0.1) = 20
    tuned = scan_cells(o, pts, lab, RES, K, free_margin=0.3, surface_offset=0.05)
    assert keys_of(tuned.occupied) == {(20, 0, 0)}  # 2.05 lands mid-voxel behind the surface
    free = keys_of(tuned.free)
    assert (16, 0, 0) in free and not {(17, 0, 0), (18, 0, 0), (19, 0, 0)} & free
    assert (0, 29, 0) in free  # no return: free up to the end
    # a measurement just in front of a boundary surface is still binned inside it
    front = scan_cells(
        o, np.array([[1.99, 0.05, 0.05]]), np.array([1]), RES, K, surface_offset=0.05
    )
    assert keys_of(front.occupied) == {(20, 0, 0)}
