"""Verified closures as a stream against what the peer acknowledged (docs/architecture.md,
"Bytes on the wire").

A robot sends its accepted closures with a peer as :class:`LoopClosures` batches, each the whole
accepted set, re-sent until the peer acknowledges it (docs/architecture.md). PCM re-decides a
pair's set whenever a closure is verified, so batch after batch repeats the same closures. Here
a batch carries every closure's keys (the set, and so what was dropped), but the relative pose,
noise and inliers only of the closures that the newest batch the peer acknowledged (``base``)
does not hold with the very same values (``fresh``).

* :class:`ClosureOutbox` (the sender): the newest batch per peer until acknowledged, in this
  compact form the first time and in full when re-sent (a peer that could not expand it gets
  everything), and in full after :meth:`ClosureOutbox.forget` (a peer that (re)appeared).
* :class:`ClosureInbox` (every receiver that needs the poses: the peer, the server) keeps the
  last :data:`HISTORY` batches of each (sender, peer) pair and expands a batch back into the
  full message, in the sender's order. A batch against a ``base`` it does not hold, or whose
  fields disagree, raises :class:`~kimera_multi_py.core.errors.MessageError` (one counted
  refusal; the sender's re-send brings the full batch).

Without loss a receiver's expansion is exactly the sender's full batch, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.comms.messages.closures import LoopClosures
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.posegraph import pair_index

HISTORY = 16  # batches kept per (sender, peer) pair, and per peer by the sender


@dataclass
class _Batch:
    """One batch's closures: their key pairs and values, row by row."""

    keys_a: np.ndarray
    keys_b: np.ndarray
    poses: np.ndarray
    sigmas: np.ndarray
    inliers: np.ndarray

    @staticmethod
    def of(msg: LoopClosures) -> _Batch:
        return _Batch(np.asarray(msg.keys_a), np.asarray(msg.keys_b), np.asarray(msg.poses), np.asarray(msg.sigmas),
                      np.asarray(msg.inliers))

    def rows(self, keys_a: np.ndarray, keys_b: np.ndarray) -> np.ndarray:
        """The row of each key pair here, or -1 (one sorted search, :func:`pair_index`)."""
        return pair_index(keys_a, keys_b, self.keys_a, self.keys_b)

    def same(self, msg: LoopClosures) -> np.ndarray:
        """Per closure of ``msg``: held here with the very same values."""
        j = self.rows(msg.keys_a, msg.keys_b)
        held = j >= 0
        if not held.any():
            return held
        k = np.where(held, j, 0)
        return (held & np.all(self.poses[k] == msg.poses, axis=(1, 2)) & np.all(self.sigmas[k] == msg.sigmas, axis=1)
                & (self.inliers[k] == msg.inliers))


def _keep(store: dict[int, _Batch], batch: int, content: _Batch) -> None:
    store[batch] = content
    while len(store) > HISTORY:
        del store[min(store)]


def is_full(msg: LoopClosures) -> bool:
    """Whether ``msg`` carries every closure's values itself."""
    return msg.base < 0 and (len(msg.fresh) == 0 or bool(np.all(msg.fresh == 1)))


def compact(full: LoopClosures, acked: tuple[int, _Batch] | None) -> LoopClosures:
    """``full`` with only the closures ``acked`` (batch number, closures) lacks carrying values.

    Only against a base at most :data:`HISTORY` batches older: the receiver keeps its last
    :data:`HISTORY` batches, and every batch it took after the base pushes one out, so a burst of
    batches sent before the acks come back would otherwise outrun what the receiver holds."""
    if acked is None or full.robot == full.peer or not len(full.keys_a) or full.batch - acked[0] > HISTORY:
        return full
    base, held = acked
    fresh = ~held.same(full)
    if fresh.all():
        return full
    return LoopClosures(robot=full.robot, peer=full.peer, batch=full.batch, keys_a=full.keys_a,
                        keys_b=full.keys_b, poses=full.poses[fresh], sigmas=full.sigmas[fresh],
                        inliers=full.inliers[fresh], base=base, fresh=fresh.view(np.uint8))


@dataclass
class ClosureOutbox:
    """The sender's side (module docstring). ``compact``: False sends every batch in full."""

    compact: bool = True
    unacked: dict[int, LoopClosures] = field(default_factory=dict)  # peer -> newest full batch not acknowledged
    sent_at: dict[int, float] = field(default_factory=dict)
    _sent: dict[int, dict[int, _Batch]] = field(default_factory=dict)  # peer -> batch -> closures
    _acked: dict[int, tuple[int, _Batch]] = field(default_factory=dict)  # peer -> newest acknowledged

    def send(self, full: LoopClosures) -> LoopClosures:
        """Record ``full`` (the agent's newest batch for its peer); return what goes on the wire."""
        peer = full.peer
        if peer == full.robot:
            return full
        self.unacked[peer] = full
        self.sent_at.pop(peer, None)  # the re-send timer starts at the next tick
        _keep(self._sent.setdefault(peer, {}), full.batch, _Batch.of(full))
        return compact(full, self._acked.get(peer)) if self.compact else full

    def acked(self, peer: int, batch: int) -> None:
        """``peer`` acknowledged ``batch``."""
        held = self._sent.get(peer, {}).get(batch)
        if held is not None and batch > self._acked.get(peer, (-1, held))[0]:
            self._acked[peer] = (batch, held)
        pending = self.unacked.get(peer)
        if pending is not None and batch >= pending.batch:
            del self.unacked[peer]

    def forget(self, peer: int) -> None:
        """``peer`` may hold nothing of ours (it (re)appeared): the next batch goes in full."""
        self._acked.pop(peer, None)

    def due(self, wall: float, period: float) -> list[LoopClosures]:
        """The unacknowledged batches whose re-send is due, in full."""
        out = []
        for peer, msg in sorted(self.unacked.items()):
            if wall - self.sent_at.setdefault(peer, wall) >= period:
                self.sent_at[peer] = wall
                out.append(msg)
        return out


@dataclass
class ClosureInbox:
    """A receiver's side (module docstring)."""

    _held: dict[tuple[int, int], dict[int, _Batch]] = field(default_factory=dict)

    def expand(self, msg: LoopClosures) -> LoopClosures:
        """The full batch ``msg`` stands for; :class:`MessageError` if it cannot be had."""
        n, m = len(msg.keys_a), len(msg.poses)
        fresh = np.asarray(msg.fresh) == 1 if len(msg.fresh) else np.ones(n, dtype=bool)
        if len(fresh) != n or int(fresh.sum()) != m:
            raise MessageError(f"LoopClosures: {len(fresh)} fresh flags ({int(fresh.sum())} set) "
                               f"for {n} closures and {m} values")
        store = self._held.setdefault((msg.robot, msg.peer), {})
        if fresh.all():
            full = msg if not len(msg.fresh) and msg.base < 0 else LoopClosures(
                robot=msg.robot, peer=msg.peer, batch=msg.batch, keys_a=msg.keys_a, keys_b=msg.keys_b,
                poses=msg.poses, sigmas=msg.sigmas, inliers=msg.inliers)
        else:
            held = store.get(msg.base)
            if held is None:
                raise MessageError(f"LoopClosures: batch {msg.batch} against batch {msg.base}, not held here")
            rows_a = held.rows(msg.keys_a[~fresh], msg.keys_b[~fresh])
            if rows_a.min() < 0:
                raise MessageError(f"LoopClosures: batch {msg.batch} keeps a closure batch {msg.base} lacks")
            poses = np.empty((n, 4, 4))
            sigmas = np.empty((n, 6))
            inliers = np.empty(n, dtype=np.int32)
            poses[fresh], sigmas[fresh], inliers[fresh] = msg.poses, msg.sigmas, msg.inliers
            poses[~fresh], sigmas[~fresh], inliers[~fresh] = held.poses[rows_a], held.sigmas[rows_a], \
                held.inliers[rows_a]
            full = LoopClosures(robot=msg.robot, peer=msg.peer, batch=msg.batch, keys_a=msg.keys_a,
                                keys_b=msg.keys_b, poses=poses, sigmas=sigmas, inliers=inliers)
        _keep(store, msg.batch, _Batch.of(full))
        return full
