"""Team-map fusion pieces: the wire form of cells, order-free fusion, team-map files."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import make_pose, so3_exp
from kimera_multi_py.mapping.octree_io import export_team_map
from kimera_multi_py.mapshare.consensus import MapConsensus, MapConsensusParams
from kimera_multi_py.mapshare.exchange import MapExchange
from kimera_multi_py.mapshare.fusion import (
    EvidenceMap,
    centralised_team_map,
    fuse_records,
    octree_cells,
    records_of,
    union_sorted,
)
from kimera_multi_py.mapshare.laplacian import LaplacianState
from kimera_multi_py.mapshare.wire import pack_cells, pack_leaves, unpack_cells, unpack_leaves

from ..mapping.helpers import K
from .test_map_consensus import robot_map, same, snapshot


def test_cells_survive_the_wire_and_bad_payloads_are_refused() -> None:
    rng = np.random.default_rng(0)
    codes = np.unique(rng.integers(0, 1 << 48, 500))
    values = rng.integers(-32768, 32767, (len(codes), K), endpoint=True).astype(np.int16)
    payload = pack_cells(codes, values)
    got_codes, got_values = unpack_cells(payload, len(codes), K, "w")
    assert np.array_equal(got_codes, codes) and np.array_equal(got_values, values)
    assert unpack_cells(pack_cells(np.zeros(0, np.int64), np.zeros((0, K), np.int16)), 0, K, "w")[0].size == 0
    with pytest.raises(MessageError, match="payload does not hold"):
        unpack_cells(payload, len(codes) + 1, K, "w")  # a lie about the size
    with pytest.raises(MessageError, match="corrupt"):
        unpack_cells(np.frombuffer(b"not zlib at all", np.uint8), 1, K, "w")
    with pytest.raises(ValueError, match="sorted"):
        pack_cells(codes[::-1], values)


def test_evidence_map_does_not_depend_on_the_order_of_updates() -> None:
    maps = {r: robot_map(r) for r in range(3)}
    records = [rec for r in maps for rec in records_of(r, maps[r])]
    ref = centralised_team_map(maps)
    rng = np.random.default_rng(1)
    for trial in range(3):
        em = EvidenceMap(maps[0].octree)
        ops = []
        for rec in records:
            half = len(rec.codes) // 2
            ops += [("cells", rec, slice(0, half)), ("cells", rec, slice(half, None)), ("pose", rec, None)]
        for k in rng.permutation(len(ops)):
            kind, rec, sl = ops[k]
            if kind == "cells":
                em.set_cells(rec.key, rec.codes[sl], rec.rows[sl])
            else:
                em.set_pose(rec.key, rec.T_ref, make_pose(so3_exp([0, 0, 0.3]), [0.5, 0, 0]) @ rec.T)
                em.set_active(rec.key, True)
                em.set_pose(rec.key, rec.T_ref, rec.T)  # moved away and back: exact
        assert same(snapshot(em.octree), snapshot(ref)), trial
        codes, rows, _ = em.evidence()
        assert np.array_equal(codes, octree_cells(ref)[0])
    em.set_active(records[0].key, False)
    assert not same(snapshot(em.octree), snapshot(ref))


def _placed_store():
    """Three robots' maps, their records and an evidence store holding every record, placed."""
    maps = {r: robot_map(r) for r in range(3)}
    records = [rec for r in maps for rec in records_of(r, maps[r])]
    em = EvidenceMap(maps[0].octree)
    for rec in records:
        em.set_cells(rec.key, rec.codes, rec.rows)
        em.set_pose(rec.key, rec.T_ref, rec.T)
        em.set_active(rec.key, True)
    return maps, records, em


def test_small_corrections_move_the_team_map_exactly() -> None:
    """Corrections of millimetres move only the cells that change voxel; after any sequence of
    them the team map is the fusion at the last poses, bit for bit."""
    maps, records, em = _placed_store()
    rng = np.random.default_rng(4)
    final = {}
    for step in range(6):
        for rec in records:
            C = make_pose(so3_exp(rng.normal(0, 2e-3, 3)), rng.normal(0, 0.01 * (step + 1), 3))
            final[rec.key] = C @ rec.T
            em.set_pose(rec.key, rec.T_ref, final[rec.key])
    ref = fuse_records([replace(rec, T=final[rec.key]) for rec in records], maps[0].octree)
    assert not same(snapshot(ref), snapshot(centralised_team_map(maps)))  # the corrections moved cells
    assert same(snapshot(em.octree), snapshot(ref))
    assert np.array_equal(em.evidence()[0], octree_cells(ref)[0])


def test_union_sorted_matches_numpy() -> None:
    a, b = np.array([1, 4, 9]), np.array([2, 4, 10, 11])
    assert union_sorted(a, b).tolist() == np.union1d(a, b).tolist()
    assert union_sorted(a, a[:2]).tolist() == a.tolist()
    assert union_sorted().size == 0


def test_team_map_files_read_back_in_octomap(tmp_path) -> None:
    import pyoctomap

    maps = {r: robot_map(r) for r in range(2)}
    nodes = {r: MapConsensus(r, maps[r], team_size=2) for r in maps}
    for n in nodes.values():
        n.set_frame(0)
    net = MapExchange(nodes)
    for k in range(4):
        net.round(float(k))
    tree = nodes[1].team_map
    out = export_team_map(tree, tmp_path / "robot1")
    assert out["bt_nodes"] == tree.num_nodes and out["ply_points"] > 0
    ot = pyoctomap.OcTree(0.1)
    assert ot.readBinary(str(tmp_path / "robot1" / "team_map.bt"))
    assert ot.size() == tree.num_nodes and ot.getNumLeafNodes() == tree.num_leaves
    assert (tmp_path / "robot1" / "team_map.ply").read_bytes().startswith(b"ply\n")


def test_tree_leaves_survive_the_wire_and_misaligned_leaves_are_refused() -> None:
    tree = robot_map(0).octree
    payload = pack_leaves(tree.codes, tree.levels, tree.values[:, 1:])
    codes, levels, values = unpack_leaves(payload, tree.num_leaves, K, "w")
    assert np.array_equal(codes, tree.codes) and np.array_equal(levels, tree.levels)
    assert np.array_equal(values, tree.values[:, 1:])
    assert np.any(tree.levels > 0)  # pruned leaves were on the wire
    bad_levels = tree.levels.copy()
    bad_levels[np.flatnonzero(tree.levels == 0)[0]] = 3  # a voxel claiming to be a big leaf
    with pytest.raises(MessageError, match="aligned"):
        unpack_leaves(pack_leaves(tree.codes, bad_levels, tree.values[:, 1:]), tree.num_leaves, K, "w")


def test_laplacian_states_split_into_messages_rebuild_the_same_copy() -> None:
    m = robot_map(1)
    a, b = LaplacianState(K + 1), LaplacianState(K + 1)
    a.absorb_own(m)
    msgs = a.message(robot=1, frame=0, degree=1, max_cells=1000)
    assert len(msgs) > 2 and all(len(x.codes) <= 1000 for x in msgs)
    for x in reversed(msgs):  # any order within the round
        b.handle(x)
    assert np.array_equal(b.copies[1].codes, a.codes) and np.array_equal(b.copies[1].values, a.values)


def test_the_evidence_store_does_not_grow_with_re_anchorings() -> None:
    """Moving the same submaps again and again (a whole pose table at a time, as a peer's tables
    arrive) leaves the store's bytes where one placement puts them, and its map the fusion."""
    maps, records, em = _placed_store()
    em.octree  # noqa: B018  (the view is part of what is held while it is built)
    placed = em.nbytes
    rng = np.random.default_rng(4)
    for _ in range(60):
        shift = make_pose(so3_exp(rng.normal(0, 0.02, 3)), rng.normal(0, 0.2, 3))
        em.set_poses([(rec.key, rec.T_ref, shift @ rec.T) for rec in records])
        em.octree  # noqa: B018
    em.set_poses([(rec.key, rec.T_ref, rec.T) for rec in records])
    em.octree  # noqa: B018
    assert em.nbytes == placed
    assert same(snapshot(em.octree), snapshot(centralised_team_map(maps)))


def test_the_evidence_store_does_not_grow_with_new_versions_of_a_submap() -> None:
    """Versions of the same cells arriving again and again with other values (as a growing
    submap's evidence does) leave the store's bytes set by what it holds now: the row palette
    keeps only the rows some cell holds."""
    maps, records, em = _placed_store()
    em.octree  # noqa: B018
    placed = em.nbytes
    rng = np.random.default_rng(5)
    for _ in range(20):
        for rec in records:
            rows = rec.rows.copy()
            rows[:, 1:] += rng.integers(-3, 4, size=rows[:, 1:].shape).astype(np.int16)
            em.set_cells(rec.key, rec.codes, rows)
    for rec in records:
        em.set_cells(rec.key, rec.codes, rec.rows)
    em.octree  # noqa: B018
    assert em.nbytes == placed
    assert same(snapshot(em.octree), snapshot(centralised_team_map(maps)))


def test_a_robots_map_consensus_holds_each_submap_once() -> None:
    """The evidence a robot holds of a submap lives in one place (the team store), as cells, a
    palette index per cell and the palette of distinct rows; what the map consensus adds beyond
    it is a version mark per cell (a byte: versions count the submap's scans)."""
    local = robot_map(0)
    mc = MapConsensus(0, local, MapConsensusParams(hold=0.0))  # every submap versioned at once
    mc.step(0.0)
    cells = sum(len(s.codes) for s in local.submaps.values())
    entries = list(mc.team.entries.values())
    palettes = sum(e.palette.nbytes for e in entries)
    assert cells > 0 and mc.nbytes - mc.team.nbytes == cells  # uint8 marks
    assert sum(e.nbytes for e in entries) == cells * (8 + 2 + 8) + palettes  # codes, index, world codes
    assert palettes < cells * 2 * (K + 1) / 4  # rows repeat: the palette is far smaller than the rows
    for sid, s in local.submaps.items():  # and gives back every row
        codes, rows = mc.team.record((0, sid))
        assert np.array_equal(codes, s.codes) and np.array_equal(rows, s.rows)
