"""Closure batches against the acknowledged batch (kimera_multi_py.comms.closure_stream): the
receiver's expansion is the sender's full batch bit for bit; what cannot be expanded is refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kimera_multi_py.comms.closure_stream import HISTORY, ClosureInbox, ClosureOutbox, is_full
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.closures import LoopClosures
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.posegraph import robot_key


def _batch(batch: int, kfs: list[tuple[int, int]], seed: int = 0, robot: int = 0, peer: int = 1) -> LoopClosures:
    """A full batch; closure (a, b)'s values depend only on (a, b, seed)."""
    poses = np.stack([np.eye(4) + np.random.default_rng((a, b, seed)).normal(0, 0.1, (4, 4))
                      for a, b in kfs]) if kfs else np.zeros((0, 4, 4))
    poses[:, 3] = [0, 0, 0, 1]
    return LoopClosures(robot=robot, peer=peer, batch=batch,
                        keys_a=np.array([robot_key(robot, a) for a, _ in kfs], np.int64),
                        keys_b=np.array([robot_key(peer, b) for _, b in kfs], np.int64),
                        poses=poses, sigmas=np.tile([0.01] * 3 + [0.05] * 3, (len(kfs), 1)),
                        inliers=np.array([10 + a for a, _ in kfs], np.int32))


def _same(a: LoopClosures, b: LoopClosures) -> bool:
    fields = ("keys_a", "keys_b", "poses", "sigmas", "inliers")
    return all(np.array_equal(getattr(a, f), getattr(b, f)) for f in fields) \
        and (a.robot, a.peer, a.batch) == (b.robot, b.peer, b.batch) and is_full(b)


def _sets(rng: np.random.Generator, n: int) -> list[list[tuple[int, int]]]:
    """PCM-like histories: closures join, some leave, some come back, order shuffled at times."""
    pool = [(int(a), int(b)) for a, b in rng.integers(0, 200, (40, 2))]
    cur: list[tuple[int, int]] = []
    out = []
    for _ in range(n):
        cur = [c for c in cur if rng.random() > 0.1] + [pool[int(i)] for i in rng.integers(0, 40, 3)]
        if rng.random() < 0.2:
            cur = [cur[int(i)] for i in rng.permutation(len(cur))]
        out.append(list(cur))
    return out


@pytest.mark.parametrize("seed", range(5))
def test_expansion_is_the_full_batch_bit_for_bit_and_later_batches_shrink(seed: int) -> None:
    rng = np.random.default_rng(seed)
    out, inbox = ClosureOutbox(), ClosureInbox()
    codec_tx, codec_rx = Codec("t0", 0, range(3)), Codec("t0", 1, range(3))
    full_bytes = sent_bytes = 0
    for batch, kfs in enumerate(_sets(rng, 30)):
        full = _batch(batch, kfs, seed=int(rng.integers(2)) if batch % 7 == 3 else 0)  # values re-decided at times
        wire = out.send(full)
        full_bytes += len(codec_tx.encode(full))
        data = codec_tx.encode(wire)
        sent_bytes += len(data)
        got = inbox.expand(codec_rx.decode(data).msg)  # type: ignore[arg-type]
        assert _same(full, got)
        if rng.random() < 0.8:  # acks get lost at times
            out.acked(1, batch)
    assert sent_bytes < 0.6 * full_bytes


def test_lost_batches_and_a_receiver_without_the_base_refuse_then_the_resend_repairs() -> None:
    out, inbox = ClosureOutbox(), ClosureInbox()
    first = _batch(0, [(1, 2), (3, 4)])
    inbox.expand(out.send(first))
    out.acked(1, 0)
    second = _batch(1, [(1, 2), (3, 4), (5, 6)])
    wire = out.send(second)
    assert not is_full(wire) and len(wire.poses) == 1 and wire.base == 0
    stranger = ClosureInbox()  # e.g. a receiver restarted after it acknowledged batch 0
    with pytest.raises(MessageError, match="not held"):
        stranger.expand(wire)
    (resend,) = out.due(0.0, 5.0) or out.due(10.0, 5.0)
    assert is_full(resend) and _same(second, stranger.expand(resend))
    assert _same(second, inbox.expand(wire))
    out.forget(1)  # the peer (re)appeared: everything in full again
    assert is_full(out.send(_batch(2, [(1, 2), (3, 4), (5, 6)])))


def test_a_burst_sent_before_the_acks_return_never_outruns_the_receivers_history() -> None:
    """Batches sent in a burst (every one received, every ack still on its way) stay expandable:
    past :data:`HISTORY` batches beyond the acknowledged one, the sender goes in full."""
    out, inbox = ClosureOutbox(), ClosureInbox()
    inbox.expand(out.send(_batch(0, [(1, 2)])))
    out.acked(1, 0)
    kfs = [(1, 2)]
    for batch in range(1, 3 * HISTORY):
        kfs = kfs + [(batch + 2, batch)]
        full = _batch(batch, kfs)
        wire = out.send(full)
        assert is_full(wire) == (batch > HISTORY)
        assert _same(full, inbox.expand(wire))


def test_intra_robot_batches_and_the_full_format_go_whole() -> None:
    out = ClosureOutbox()
    intra = _batch(0, [(1, 2)], peer=0)
    assert out.send(intra) is intra and not out.unacked
    plain = ClosureOutbox(compact=False)
    plain.send(_batch(0, [(1, 2)]))
    plain.acked(1, 0)
    assert is_full(plain.send(_batch(1, [(1, 2), (3, 4)])))


def test_inconsistent_batches_are_refused() -> None:
    out, inbox = ClosureOutbox(), ClosureInbox()
    inbox.expand(out.send(_batch(0, [(1, 2), (3, 4)])))
    out.acked(1, 0)
    wire = out.send(_batch(1, [(1, 2), (3, 4), (5, 6)]))
    bad = [
        dataclasses.replace(wire, fresh=wire.fresh[:-1]),  # fewer flags than closures
        dataclasses.replace(wire, fresh=np.ones(3, np.uint8)),  # more set than values
        dataclasses.replace(wire, base=7),  # a base never sent
        dataclasses.replace(wire, keys_b=wire.keys_b[::-1].copy()),  # keeps closures the base lacks
    ]
    for msg in bad:
        with pytest.raises(MessageError):
            ClosureInbox().expand(msg) if msg.base == 7 else _fresh_inbox().expand(msg)


def _fresh_inbox() -> ClosureInbox:
    inbox = ClosureInbox()
    inbox.expand(_batch(0, [(1, 2), (3, 4)]))
    return inbox


def test_fuzzed_compact_batches_are_refused_or_whole_never_crash() -> None:
    """Byte mutations of an encoded compact batch: the codec or the expansion refuses
    (MessageError), or the expansion is a whole batch (as many values as closures, finite)."""
    out = ClosureOutbox()
    out.send(_batch(0, [(1, 2), (3, 4), (5, 6)]))
    out.acked(1, 0)
    wire = out.send(_batch(1, [(1, 2), (3, 4), (5, 6), (7, 8)]))
    data = Codec("t0", 0, range(3)).encode(wire)
    rng = np.random.default_rng(0)
    refused = whole = 0
    for _ in range(2000):
        b = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            j = int(rng.integers(0, len(b)))
            b[j] = int(rng.integers(256)) if rng.integers(2) else b[j] ^ (1 << int(rng.integers(8)))
        inbox = ClosureInbox()
        inbox.expand(_batch(0, [(1, 2), (3, 4), (5, 6)]))
        try:
            msg = Codec("t0", 1, range(3)).decode(bytes(b)).msg
            assert isinstance(msg, LoopClosures)
            got = inbox.expand(msg) if msg.robot == 0 else None
        except MessageError:
            refused += 1
            continue
        if got is not None:
            assert len(got.poses) == len(got.keys_a) == len(got.inliers) and np.isfinite(got.poses).all()
        whole += 1
    assert refused > 0 and whole > 0 and refused + whole == 2000
