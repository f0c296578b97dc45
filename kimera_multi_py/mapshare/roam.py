"""ROAM's map fusion rule, exactly as its public code does it: the ``roam`` baseline (docs/algorithms/map_consensus.md).

Every period a robot publishes its full pruned tree; a receiver fuses at most one peer tree per
period (the first to arrive) with ``h_i <- clip(h_i + w h_j)``: incoming pruned leaves are
expanded to full depth, a cell only the peer has becomes ``w h_j``, classes are cut back to the
top 3 plus "others" and every entry is clamped to +-5. ROAM pays 36 B per node of the tree,
inner nodes included. This module reproduces the rule and its double counting on purpose; it is
the reference the exact scheme is measured against, not something to improve.
"""

from __future__ import annotations

import numpy as np

from kimera_multi_py.comms.messages.maps import RoamMap
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.mapping.semantic_octree import SemanticOctree
from kimera_multi_py.mapping.submaps import SubmapMap
from kimera_multi_py.mapshare.fusion import octree_cells, union_sorted
from kimera_multi_py.mapshare.wire import pack_leaves, unpack_leaves

ROAM_NODE_BYTES = 36  # float occupancy, 3 B colour, 3 x (class colour + float) + others, child mask
_I16 = np.iinfo(np.int16)


def sparse_diff(
    new: tuple[np.ndarray, np.ndarray], old: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """``new - old`` of two sparse row sets (sorted codes), over the union of their codes."""
    codes = union_sorted(new[0], old[0])
    out = np.zeros((len(codes), new[1].shape[1]), dtype=np.int64)
    out[np.searchsorted(codes, new[0])] += new[1]
    out[np.searchsorted(codes, old[0])] -= old[1]
    return codes, out


class RoamFusion:
    """One robot's ROAM map: its own observations plus the peer trees it fused."""

    def __init__(self, template: SemanticOctree, weight: float = 0.2, top_k: int = 3, clamp: float = 5.0) -> None:
        if not 0.0 < weight:
            raise ValueError(f"roam weight must be positive, got {weight}")
        self.tree = template.empty_like(top_k=top_k, h_min=-clamp, h_max=clamp)
        self.weight = float(weight)
        k1 = self.tree.num_classes + 1
        self._own: tuple[np.ndarray, np.ndarray] = (np.zeros(0, np.int64), np.zeros((0, k1), np.int64))
        self.fused = 0

    def absorb_own(self, local: SubmapMap) -> int:
        """Add what the robot observed since the last call (its map's evidence change)."""
        codes, rows, _ = local.evidence()
        now = (codes, rows.astype(np.int64))
        dc, drows = sparse_diff(now, self._own)
        self._own = now
        _, known = self.tree.cell_values(dc)
        changed = np.any(drows != 0, axis=1) | ~known  # new cells start at the prior
        dc, drows = dc[changed], drows[changed]
        if len(dc) == 0:
            return 0
        self.tree.add(dc, np.clip(drows, _I16.min, _I16.max).astype(np.int16))
        return int(len(dc))

    def message(self, robot: int, rnd: int, frame: int) -> RoamMap:
        """The full pruned tree as ROAM publishes it."""
        t = self.tree
        return RoamMap(robot=robot, round=rnd, frame=frame, nodes=t.num_nodes, leaves=t.num_leaves,
                       classes=t.num_classes, payload=pack_leaves(t.codes, t.levels, t.values[:, 1:]))

    def fuse(self, msg: RoamMap) -> int:
        """``h_i <- clip(h_i + w h_j)`` over the peer's tree expanded to full depth; returns cells."""
        k = self.tree.num_classes
        if msg.classes != k:
            raise MessageError(f"RoamMap.classes: expected {k} classes, got {msg.classes}")
        leaf_codes, levels, values = unpack_leaves(msg.payload, msg.leaves, k, "RoamMap.payload")
        peer = self.tree.empty_like()
        rows = np.zeros((len(leaf_codes), k + 1), np.int16)
        rows[:, 1:] = values
        peer._set_arrays(leaf_codes, levels, rows)
        codes, h_j = octree_cells(peer)
        if len(codes) == 0:
            return 0
        _, known = self.tree.cell_values(codes)
        delta = np.round(self.weight * h_j.astype(np.float64)).astype(np.int64)
        delta[~known] -= self.tree.model.prior_row.astype(np.int64)  # a cell only the peer has: w h_j
        delta[:, 0] = 0
        self.tree.add(codes, np.clip(delta, _I16.min, _I16.max).astype(np.int16))
        self.fused += 1
        return int(len(codes))
