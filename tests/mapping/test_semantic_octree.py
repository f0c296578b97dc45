import numpy as np
import pytest

from kimera_multi_py.mapping import SCALE, ObservationModel, SemanticOctree, scan_cells

from .helpers import (
    CEILING,
    CHAIR,
    FLOOR,
    HUMAN,
    TABLE,
    WALL,
    K,
    ReferenceMap,
    canonical_leaves,
    flip_labels,
    room_scan,
    tree_leaves,
)

RES = 0.1
ORIGINS = [
    np.array(p)
    for p in (
        [0.0, 0.0, 1.0],
        [-1.5, 1.0, 1.2],
        [1.0, -1.2, 0.9],
        [-2.0, -1.5, 1.5],
        [0.5, 1.5, 1.1],
    )
]


def fill(tree, scans=10, n=4000, noise=0.1, seed=0):
    for i in range(scans):
        o = ORIGINS[i % len(ORIGINS)]
        p, lab = room_scan(o, n, seed=seed + i, noise=noise)
        tree.insert_scan(o, p, lab)
    return tree


def test_matches_a_per_voxel_reference_and_prunes_canonically():
    tree = SemanticOctree(RES, K, dynamic_classes=[HUMAN], h_min=-3.5, h_max=3.5)
    ref = ReferenceMap(tree.model)
    for i in range(8):
        o = ORIGINS[i % 3]
        p, lab = room_scan(
            o,
            2500,
            seed=i,
            noise=0.1,
            human=(np.array([-1.0 + 0.3 * i, 0.5, 0.05]), np.array([-0.5 + 0.3 * i, 1.0, 1.8])),
        )
        cells = scan_cells(o, p, lab, RES, K, dynamic_labels=(HUMAN,))
        codes, rows = tree.model.deltas(cells)
        ref.add(codes, rows)
        tree.insert_cells(cells)
        got, known = tree.cell_values(np.array(sorted(ref.cells)))
        assert known.all()
        assert np.array_equal(got, np.array([ref.cells[c] for c in sorted(ref.cells)]))
        assert tree_leaves(tree) == canonical_leaves(ref.cells)
    assert tree.levels.max() >= 2  # free space collapsed into coarse cells
    assert tree.num_leaves < len(ref.cells)


def test_room_geometry_and_semantics():
    tree = fill(SemanticOctree(RES, K))
    probes = {
        WALL: [[-3.05, 0.33, 1.31], [3.05, -1.02, 0.74], [0.42, 2.55, 2.02]],
        FLOOR: [[-1.33, -1.87, 0.05], [0.4, 0.8, 0.05]],
        CEILING: [[0.61, -0.3, 2.55]],
        TABLE: [[1.55, -0.15, 0.75], [1.05, -0.2, 0.5]],
        0: [[0.0, 0.5, 1.5], [-1.0, -1.0, 0.8], [2.0, 1.5, 2.0]],
        -1: [[0.0, 0.0, 5.0], [10.0, 0.0, 1.0], [1.6, -0.1, 0.4]],  # outside; inside the table
    }
    for cls, pts in probes.items():
        assert np.all(tree.class_at(np.array(pts)) == cls), cls
    pts = np.array(probes[WALL] + probes[0] + probes[-1])
    pmf = tree.pmf_at(pts)
    known = ~np.isnan(pmf[:, 0])
    assert np.allclose(pmf[known].sum(1), 1.0)
    occ = tree.occupancy_at(pts)
    assert np.all(occ[:3] > 0.5) and np.all(occ[3:6] < 0.2) and np.all(np.isnan(occ[6:]))
    assert np.all(np.isnan(tree.logodds_at(np.array(probes[-1]))))


def test_clamping_makes_saturated_cells_identical():
    tree = SemanticOctree(RES, K, h_min=-3.0, h_max=3.5)
    o = ORIGINS[0]
    p, lab = room_scan(o, 20000, seed=1)
    for _ in range(12):
        tree.insert_scan(o, p, lab)
    v = tree.values
    assert v.min() >= round(-3.0 * SCALE) and v.max() <= round(3.5 * SCALE)
    assert np.all(v[:, 0] == 0)
    free = np.argmax(v, axis=1) == 0
    assert len(np.unique(v[free], axis=0)) == 1  # every free leaf at h_min on every class
    wall = np.argmax(v, axis=1) == WALL
    rows, counts = np.unique(v[wall], axis=0, return_counts=True)
    top = rows[np.argmax(counts)]  # cells at edges keep two classes (their rays see both)
    assert counts.max() > 0.9 * wall.sum()
    assert top[WALL] == round(3.5 * SCALE) and np.all(
        np.delete(top, [0, WALL]) == round(-3.0 * SCALE)
    )
    # identical saturated cells prune: coarse leaves stand for many voxels
    assert tree.levels.max() >= 3
    assert (8.0**tree.levels).sum() > 2 * tree.num_leaves


def test_dynamic_classes_never_enter_the_map():
    def run(dynamic):
        tree = SemanticOctree(RES, K, dynamic_classes=dynamic)
        for i in range(10):
            x = -2.0 + 0.4 * i  # a person walking across the room
            human = (np.array([x, -2.0, 0.05]), np.array([x + 0.5, -1.5, 1.8]))
            o = ORIGINS[i % 2]
            p, lab = room_scan(o, 3000, seed=i, human=human)
            assert (lab == HUMAN).sum() > 10
            tree.insert_scan(o, p, lab)
        return tree

    assert np.any(np.argmax(run(()).values, axis=1) == HUMAN)  # control: unmasked, humans stick
    masked = run((HUMAN,))
    assert not np.any(np.argmax(masked.values, axis=1) == HUMAN)
    # the space the person walked through is free where it was seen
    assert masked.class_at(np.array([[0.0, -1.75, 1.0]]))[0] == 0


def test_label_noise_is_voted_out():
    o = ORIGINS[0]
    p, truth = room_scan(o, 4000, seed=5)
    rng = np.random.default_rng(5)
    tree = SemanticOctree(RES, K)
    tree.insert_scan(o, p, flip_labels(truth, 0.2, rng))
    once = tree.class_at(p)
    for _ in range(9):
        tree.insert_scan(o, p, flip_labels(truth, 0.2, rng))
    after = tree.class_at(p)
    assert np.mean(once == truth) < 0.9
    assert np.mean(after == truth) > 0.99


def test_top_k_keeps_a_few_classes_and_prunes_more():
    full = fill(SemanticOctree(RES, K))
    top = fill(SemanticOctree(RES, K, top_k=2))
    for row in top.values[:, 1:]:
        assert len(np.unique(row)) <= 3
    assert top.num_leaves <= full.num_leaves
    probe = np.array([[-3.05, 0.33, 1.31], [1.55, -0.15, 0.75], [0.0, 0.5, 1.5]])
    assert np.array_equal(top.class_at(probe), [WALL, TABLE, 0])


def test_set_and_remove_cells_keep_the_tree_canonical():
    tree = fill(SemanticOctree(RES, K), scans=4, n=2000)
    cells = {int(c): r.copy() for c, r in zip(*_voxels(tree), strict=True)}
    rng = np.random.default_rng(3)
    codes = np.array(sorted(cells))
    pick = np.sort(rng.choice(codes, 200, replace=False))
    rows = np.zeros((200, K + 1), np.int16)
    rows[:, 1:] = rng.integers(-3000, 3000, (200, K))
    tree.set_cells(pick, rows)
    for c, r in zip(pick.tolist(), rows, strict=True):
        cells[c] = r
    assert tree_leaves(tree) == canonical_leaves(cells)
    drop = np.sort(rng.choice(codes, 300, replace=False))
    tree.remove_cells(drop)
    for c in drop.tolist():
        cells.pop(c)
    assert tree_leaves(tree) == canonical_leaves(cells)
    _, known = tree.cell_values(drop)
    assert not known.any()


def _voxels(tree):
    """All finest voxels of a tree (expanding coarse leaves) and their rows."""
    codes, rows = [], []
    for c, lv, r in zip(tree.codes, tree.levels, tree.values, strict=True):
        n = 8 ** int(lv)
        codes.append(np.arange(c, c + n, dtype=np.int64))
        rows.append(np.repeat(r[None], n, axis=0))
    return np.concatenate(codes), np.concatenate(rows)


def test_leaves_counts_and_empty_queries():
    empty = SemanticOctree(RES, K)
    assert empty.num_leaves == 0 and empty.num_nodes == 0
    assert np.array_equal(empty.class_at(np.zeros((2, 3))), [-1, -1])
    assert np.isnan(empty.occupancy_at(np.zeros((1, 3)))).all()
    tree = fill(SemanticOctree(RES, K), scans=3, n=2000)
    lv = tree.leaves()
    assert np.allclose(lv.sizes, RES * 2.0**tree.levels)
    assert len(list(tree.iter_leaves())) == tree.num_leaves
    c, size, h = next(iter(tree.iter_leaves()))
    assert size == lv.sizes[0] and np.allclose(h, lv.logodds[0])
    # every leaf centre finds its own leaf
    assert np.array_equal(tree.find(lv.centers), np.arange(tree.num_leaves))
    assert tree.num_nodes > tree.num_leaves
    assert tree.nbytes == tree.num_leaves * (8 + 1 + 2 * (K + 1))


def test_observation_model():
    m = ObservationModel(K)
    prior = np.full(K, m.prior)
    occ = lambda h: np.log(np.exp(h).sum())  # noqa: E731 - occupancy log-odds against free
    assert occ(prior) == pytest.approx(0.0)
    hit = m.hit_rows(np.eye(K + 1, dtype=int)[[WALL]])[0, 1:] / SCALE
    assert occ(prior + hit) == pytest.approx(0.85, abs=2e-3)
    assert np.argmax(hit) + 1 == WALL and hit[CHAIR - 1] < 0
    assert np.allclose(m.miss_row[1:] / SCALE, -0.4, atol=1e-3)
    for bad in ({"h_min": 1.0}, {"h_max": 40.0}, {"miss": 0.2}, {"label_accuracy": 1.0}):
        with pytest.raises(ValueError):
            ObservationModel(K, **bad)
    with pytest.raises(ValueError):
        SemanticOctree(0.0, K)
    with pytest.raises(ValueError):
        SemanticOctree(RES, K, dynamic_classes=[K + 1])


@pytest.mark.parametrize("top_k", [None, 3])
def test_filling_an_empty_tree_in_one_batch_equals_filling_it_update_by_update(top_k):
    """``set_cells`` on an empty tree prunes the whole batch at once: the same leaves as the
    same cells written into a tree that already holds something (the incremental path)."""
    from kimera_multi_py.mapping.octree_block import BLOCK_SHIFT

    rng = np.random.default_rng(7)
    tree = SemanticOctree(0.1, 6, top_k=top_k)
    # whole blocks, whole level-2 nodes and scattered voxels, with few distinct rows so that
    # many sibling groups are identical
    base = np.int64(5) << BLOCK_SHIFT
    codes = np.unique(np.concatenate([base + np.arange(1 << BLOCK_SHIFT), (base << 1) + np.arange(4096),
                                      rng.integers(0, 1 << 40, 20000)]))
    palette = rng.integers(-3000, 3000, (3, 7)).astype(np.int16)
    palette[:, 0] = 0
    rows = palette[rng.integers(1, 3, len(codes))]  # scattered voxels: two values
    rows[codes >> BLOCK_SHIFT == 5] = palette[0]  # one whole block of one value
    pick = (codes >> 6) % 3  # level-2 nodes of one value each, some equal to their neighbours
    second = codes >> BLOCK_SHIFT == 10
    rows[second] = palette[pick[second]]
    batch = tree.empty_like()
    batch.set_cells(codes, rows)
    far = np.array([np.int64(1) << 50])
    one_by_one = tree.empty_like()
    one_by_one.set_cells(far, rows[:1])
    for part in np.array_split(np.arange(len(codes)), 7):
        one_by_one.set_cells(codes[part], rows[part])
    one_by_one.remove_cells(far)
    assert np.any(batch.levels == 5) and np.any(batch.levels == 2)
    for name in ("codes", "levels", "values"):
        assert np.array_equal(getattr(batch, name), getattr(one_by_one, name)), name
