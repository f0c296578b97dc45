"""The coarse space of the distributed Gauss–Newton solve: rigid motions of pose chunks.

Block Jacobi over robots solves bending inside a robot exactly but leaves the smooth bending
of the whole team (slow for CG, and all of it when the robots' trajectories interleave, as on
parking-garage where nearly every pose is public). A two-level preconditioner adds a coarse
correction ``P A_c⁻¹ Pᵀ``: every robot cuts its poses into chunks of ``size`` consecutive
poses, and a chunk moves rigidly (``δᵢ = Ad(Xᵢ⁻¹) ξ_c``: the right perturbation of pose ``i``
under a world motion ``ξ_c``). ``A_c = Pᵀ H P`` is small; each robot computes its rows (its
chunks against its own and its neighbours' chunks), the team exchanges them once per
linearisation and every robot factors the same ``A_c``. A coarse solve then needs only every
robot's restriction ``P_rᵀ v_r`` (6 floats per chunk), and the prolongation onto a neighbour's
pose is computed locally from its pose and chunk (both known).

Chunk ids are ``robot << 32 | chunk``; all robots number the coarse unknowns by sorted id.

Recycling (Krylov subspace recycling across the Gauss–Newton steps): the coarse space also
holds the team's last few steps ``d`` (each robot knows its own part and, from the step
exchange, its part at the inter-robot edges' far ends). Truncated CG leaves the same smooth
error in the next linear system (the line search then picks steps of 1.5-3x), so the old step
is close to the slow modes of the new one. Their coarse rows ``Pᵀ H d`` and ``dᵀ H d`` are
recomputed with the current ``H`` every linearisation (6 floats per chunk, one block per robot)
and their restriction ``dᵀ v`` travels as one more row of ``coarse`` (id ``RECYCLE | robot``).
The extended coarse matrix is solved by block elimination; directions whose Schur complement
is not clearly positive (a step in the span of the chunks or of the other steps) are dropped.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from kimera_multi_py.core.geometry import inverse
from kimera_multi_py.pgo.linear import LinearSystemError, LocalSystem, adjoint

INDEX_MASK = (1 << 56) - 1  # a pose key's index bits (robot_key)
RECYCLE = 1 << 62  # coarse ids of the recycled steps: restriction ``RECYCLE | robot``, rows
MAX_RECYCLE = 6  # recycled steps in one 6-wide row at most


def chunk_ids(robot: int | np.ndarray, index: np.ndarray, size: int) -> np.ndarray:
    """Global chunk id of pose ``index`` of ``robot``."""
    return (np.asarray(robot, dtype=np.int64) << 32) | (np.asarray(index, dtype=np.int64) // size)


class CoarseRows:
    """One robot's part of the coarse space at a linearisation point."""

    def __init__(self, robot: int, poses: np.ndarray, peer_poses: np.ndarray,
                 inter_peer: np.ndarray, inter_peer_key: np.ndarray, size: int,
                 keep: np.ndarray, peer_anchor: np.ndarray) -> None:
        n = len(poses)
        self.n = n
        self.local_chunk = np.arange(n) // size
        self.num_chunks = int(self.local_chunk.max()) + 1 if n else 0
        self.own_ids = chunk_ids(robot, np.arange(self.num_chunks) * size, size)
        self.P_own = adjoint(inverse(poses)) * keep.reshape(n, 6)[:, :, None]
        self.P_peer = adjoint(inverse(peer_poses)) if len(peer_poses) else np.zeros((0, 6, 6))
        self.P_peer[peer_anchor] = 0.0  # a frame root's first pose does not move
        self.peer_ids = chunk_ids(inter_peer, inter_peer_key & INDEX_MASK, size)
        rows = (6 * np.arange(n))[:, None, None] + np.arange(6)[None, :, None]
        cols = (6 * self.local_chunk)[:, None, None] + np.arange(6)[None, None, :]
        shape = self.P_own.shape
        self.P = sp.coo_matrix((self.P_own.ravel(), (np.broadcast_to(rows, shape).ravel(),
                                                     np.broadcast_to(cols, shape).ravel())),
                               shape=(6 * n, 6 * self.num_chunks)).tocsr()

    def rows(self, system: LocalSystem) -> tuple[np.ndarray, np.ndarray]:
        """Upper-triangle blocks of this robot's rows of ``A_c``: ids ``(b, 2)``, ``(b, 6, 6)``.

        Own × own from the own block; own × neighbour chunk from the inter-robot couplings
        (sent by the robot with the smaller chunk id; the other one holds the transpose).
        """
        c = self.num_chunks
        own = (self.P.T @ system.H @ self.P)
        own = own.toarray() if sp.issparse(own) else np.asarray(own)
        blocks = own.reshape(c, 6, c, 6).transpose(0, 2, 1, 3)
        a, b = np.triu_indices(c)
        nz = np.abs(blocks[a, b]).reshape(len(a), -1).max(axis=1) > 0
        ids = [np.stack([self.own_ids[a[nz]], self.own_ids[b[nz]]], axis=1)]
        vals = [blocks[a[nz], b[nz]]]
        if len(self.peer_ids):
            Po = self.P_own[system.inter_own]
            blk = np.swapaxes(Po, 1, 2) @ system.coupling @ self.P_peer
            mine = self.own_ids[self.local_chunk[system.inter_own]]
            up = mine < self.peer_ids
            pairs, inv = np.unique(np.stack([mine[up], self.peer_ids[up]], axis=1), axis=0,
                                   return_inverse=True)
            acc = np.zeros((len(pairs), 6, 6))
            np.add.at(acc, inv.ravel(), blk[up])
            ids.append(pairs)
            vals.append(acc)
        return np.concatenate(ids).astype(np.int64), np.concatenate(vals)

    def restrict(self, v: np.ndarray) -> np.ndarray:
        """``P_rᵀ v_r`` ``(chunks, 6)``."""
        return np.asarray(self.P.T @ v).reshape(-1, 6)


def recycled_rows(coarse: CoarseRows, system: LocalSystem, steps: list[tuple[np.ndarray, np.ndarray]]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """This robot's rows of the recycled steps ``(own (n, 6), far ends (k, 6))``: per own chunk
    ``P_cᵀ H D`` ``(6, k)`` and its share ``D_rᵀ (H D)_r`` of ``Dᵀ H D``, packed flat (chunk
    order) into 6x6 blocks with pairs ``(RECYCLE | robot, RECYCLE | i)``."""
    HD = np.stack([system.multiply(own.ravel(), peer) for own, peer in steps], axis=1)  # (6n, k)
    D = np.stack([own.ravel() for own, _ in steps], axis=1)
    flat = np.concatenate([np.asarray(coarse.P.T @ HD).ravel(), (D.T @ HD).ravel()])
    blocks = np.zeros(-(-len(flat) // 36) * 36)
    blocks[:len(flat)] = flat
    robot = int(coarse.own_ids[0] >> 32) if len(coarse.own_ids) else 0
    nb = len(blocks) // 36
    pairs = np.stack([np.full(nb, RECYCLE | robot), RECYCLE | np.arange(nb)], axis=1)
    return pairs.astype(np.int64), blocks.reshape(nb, 6, 6)


def recycled_restriction(robot: int, steps: list[tuple[np.ndarray, np.ndarray]], v: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """``D_rᵀ v_r`` as one coarse row (id ``RECYCLE | robot``, padded to 6)."""
    row = np.zeros((1, 6))
    for j, (own, _) in enumerate(steps):
        row[0, j] = own.ravel() @ v
    return np.array([RECYCLE | robot], dtype=np.int64), row


class CoarseSolver:
    """``A_c`` assembled from every robot's rows (the same on every robot), factored."""

    def __init__(self, ids: list[np.ndarray], blocks: list[np.ndarray], chunks: list[np.ndarray]
                 ) -> None:
        allc = np.concatenate(chunks)
        self.order = np.sort(allc[allc < RECYCLE])
        m = len(self.order)
        A: np.ndarray = np.zeros((m, 6, m, 6))
        self.k = 0  # recycled directions in use
        for pair, blk in zip(ids, blocks, strict=True):
            keep = (pair[:, 0] < RECYCLE) & (pair[:, 1] < RECYCLE) if len(pair) else np.zeros(0, dtype=bool)
            if not len(pair) or not keep.any():
                continue
            pair, blk = pair[keep], blk[keep]
            i, j = np.searchsorted(self.order, pair[:, 0]), np.searchsorted(self.order, pair[:, 1])
            np.add.at(A, (i, slice(None), j, slice(None)), blk)  # type: ignore[arg-type]  # numpy's stubs: no slices
            off = i != j
            np.add.at(A, (j[off], slice(None), i[off], slice(None)),  # type: ignore[arg-type]
                      np.swapaxes(blk[off], 1, 2))
        A = A.reshape(6 * m, 6 * m)
        # A_c = PᵀHP is positive semi-definite up to the float32 rounding of its blocks (and
        # near-singular on degenerate information matrices): shift its diagonal until it factors
        diag = np.maximum(np.abs(np.diagonal(A)), 1e-12 * max(float(np.abs(np.diagonal(A)).max(initial=0.0)), 1e-300))
        for shift in (1e-10, 1e-7, 1e-4, 1e-2, 1.0):
            try:
                self._factor = sla.cho_factor(A + np.diag(shift * diag))
                break
            except np.linalg.LinAlgError:
                continue
        else:
            raise LinearSystemError("coarse matrix not positive definite")

    def extend(self, ids: list[np.ndarray], blocks: list[np.ndarray], chunks: list[np.ndarray],
               k: int) -> None:
        """Add ``k`` recycled steps from every robot's :func:`recycled_rows` (0: none);
        ``chunks`` are the coarse ids each robot sent with them (its own chunks first)."""
        self.k = 0
        if k <= 0:
            return
        m = len(self.order)
        B: np.ndarray = np.zeros((m, 6, k))
        C = np.zeros((k, k))
        for pair, blk, own in zip(ids, blocks, chunks, strict=True):
            rec = pair[:, 0] >= RECYCLE if len(pair) else np.zeros(0, dtype=bool)
            if not rec.any():
                continue
            own = own[own < RECYCLE]
            flat = blk[rec][np.argsort(pair[rec, 1])].ravel()
            nb = 6 * k * len(own)
            B[np.searchsorted(self.order, own)] += flat[:nb].reshape(len(own), 6, k)
            C += flat[nb:nb + k * k].reshape(k, k)
        B = B.reshape(6 * m, k)
        C = 0.5 * (C + C.T)
        AinvB = np.asarray(sla.cho_solve(self._factor, B)).reshape(6 * m, k)
        S = C - B.T @ AinvB
        w, V = np.linalg.eigh(0.5 * (S + S.T))
        ok = w > 1e-3 * max(float(np.max(np.diag(C), initial=0.0)), 1e-300)
        if not ok.any():
            return
        self.k = k
        self._B, self._AinvB = B, AinvB
        self._Sinv = (V[:, ok] / w[ok]) @ V[:, ok].T

    def solve(self, chunks: list[np.ndarray], restricted: list[np.ndarray]
              ) -> tuple[np.ndarray, np.ndarray]:
        """The coarse solution from every robot's ``(coarse ids, restriction)``: ``(m, 6)`` at
        the chunks and ``(k,)`` at the recycled steps."""
        rhs = np.zeros((len(self.order), 6))
        g = np.zeros(max(self.k, 1))
        for c, v in zip(chunks, restricted, strict=True):
            rec = c >= RECYCLE
            rhs[np.searchsorted(self.order, c[~rec])] += v[~rec]
            if self.k and rec.any():
                g += v[rec][:, :self.k].sum(axis=0)
        y = np.asarray(sla.cho_solve(self._factor, rhs.ravel()))
        if not self.k:
            return y.reshape(-1, 6), np.zeros(0)
        z = self._Sinv @ (g - self._B.T @ y)
        return (y - self._AinvB @ z).reshape(-1, 6), z

    def prolong(self, y: np.ndarray, ids: np.ndarray, P: np.ndarray) -> np.ndarray:
        """``P y`` at poses in chunks ``ids`` ``(k,)`` with rigid maps ``P`` ``(k, 6, 6)``."""
        if not len(ids):
            return np.zeros((0, 6))
        return np.einsum("kij,kj->ki", P, y[np.searchsorted(self.order, ids)])
