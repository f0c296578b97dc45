"""The public-pose stream (kimera_multi_py.pgo.pose_stream): round trips, loss and reordering,
corrupt bytes refused, and the same distributed optimum for far fewer bytes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.pgo import PoseDeltas, PublicPoses
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import inverse, make_pose, so3_exp, so3_log
from kimera_multi_py.pgo.pose_stream import PoseDecoder, PoseEncoder, PoseStreamParams
from kimera_multi_py.workflow.pgo_benchmark import run_pgo

P = PoseStreamParams()
KEYS = np.arange(100, 140, dtype=np.int64)


def _walk(rounds: int, seed: int = 0) -> list[np.ndarray]:
    """Poses that converge: big steps first, then ever smaller, some poses still at the end."""
    rng = np.random.default_rng(seed)
    poses = make_pose(so3_exp(rng.normal(0, 1, (len(KEYS), 3))), rng.uniform(-50, 50, (len(KEYS), 3)))
    out = []
    for r in range(rounds):
        step = 0.5 * 0.6**r * rng.random(len(KEYS))[:, None]
        step[rng.random(len(KEYS)) < 0.3] = 0.0  # some poses rest this round
        poses = poses @ make_pose(so3_exp(0.1 * step * rng.normal(size=(len(KEYS), 3))),
                                  step * rng.normal(size=(len(KEYS), 3)))
        out.append(poses)
    return out


def _msg(r: int, poses: np.ndarray, settled: bool = True) -> PublicPoses:
    return PublicPoses(robot=1, round=r, keys=KEYS, poses=poses, settled=settled)


def _error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    d = inverse(a) @ b
    return float(np.abs(d[:, :3, 3]).max() + np.abs(a[:, :3, 3] - b[:, :3, 3]).max()), \
        float(np.linalg.norm(so3_log(d[:, :3, :3]), axis=1).max())


def test_round_trip_holds_every_pose_within_the_tolerance() -> None:
    enc, dec = PoseEncoder(P), PoseDecoder()
    kinds = []
    for r, poses in enumerate(_walk(60)):
        sent = enc.encode(_msg(r, poses))
        kinds.append(type(sent).__name__ if sent is not None else None)
        if sent is None:
            continue
        got = dec.decode(sent)
        assert got is not None and np.array_equal(got.keys, KEYS) and got.round == r
        dt, dr = _error(poses, got.poses)
        assert dt <= 2 * P.translation_tol + 1e-9 and dr <= 2 * P.rotation_tol + 1e-12
    # keyframes on the first round and every full_every rounds, deltas between, silence at the end
    assert [r for r, k in enumerate(kinds) if k == "PublicPoses"] == [0, 20, 40]
    assert "PoseDeltas" in kinds and None in kinds[41:]


def test_keyframes_when_the_keys_or_the_settled_flag_change() -> None:
    enc = PoseEncoder(P)
    poses = _walk(3)
    assert isinstance(enc.encode(_msg(0, poses[0])), PublicPoses)
    assert isinstance(enc.encode(_msg(1, poses[1])), PoseDeltas)
    assert isinstance(enc.encode(_msg(2, poses[2], settled=False)), PublicPoses)
    assert enc.encode(_msg(3, poses[2], settled=False)) is None  # nothing moved
    fewer = PublicPoses(robot=1, round=4, keys=KEYS[:-1], poses=poses[2][:-1], settled=False)
    assert isinstance(enc.encode(fewer), PublicPoses)


def test_while_no_pose_moves_a_repeated_keyframe_waits_quiet_every_rounds() -> None:
    enc = PoseEncoder(P)
    poses = _walk(2)
    end = P.full_every + 2 * P.quiet_every
    kinds = [type(enc.encode(_msg(r, poses[0]))).__name__ for r in range(end + 1)]
    # every keyframe goes out twice, full_every rounds apart; then one every quiet_every rounds
    assert [r for r, k in enumerate(kinds) if k == "PublicPoses"] == \
        [0, P.full_every, P.full_every + P.quiet_every, end]
    # once a pose moves, the next keyframe is full_every rounds after the last one again
    assert isinstance(enc.encode(_msg(end + 1, poses[1])), PoseDeltas)
    assert enc.encode(_msg(end + P.full_every - 1, poses[1])) is None
    assert isinstance(enc.encode(_msg(end + P.full_every, poses[1])), PublicPoses)


def test_lost_and_reordered_messages_are_repaired_by_the_next_keyframe() -> None:
    rng = np.random.default_rng(5)
    enc, dec = PoseEncoder(P), PoseDecoder()
    walk = _walk(45, seed=2)
    sent = [(r, m) for r, poses in enumerate(walk) if (m := enc.encode(_msg(r, poses))) is not None]
    kept = [(r, m) for r, m in sent if r in (20, 40) or rng.random() > 0.3]  # 30 % lost (not the last keyframes)
    kept[1], kept[2] = kept[2], kept[1]  # and two delivered out of order
    assert len(kept) < len(sent)
    held = None
    for r, m in kept:
        if r == 40:
            assert isinstance(m, PublicPoses)  # the keyframe: the receiver holds the sender's poses again
            out = dec.decode(m)
            assert out is not None and np.array_equal(out.poses, walk[40])
        got = dec.decode(m)
        held = got.poses if got is not None else held
    assert held is not None
    dt, dr = _error(walk[-1], held)
    assert dt <= 2 * P.translation_tol + 1e-9 and dr <= 2 * P.rotation_tol + 1e-12
    # a delta against a keyframe this robot never got is unusable, and counted
    fresh = PoseDecoder()
    late = next(m for r, m in sent if isinstance(m, PoseDeltas) and 20 < r < 40)
    assert fresh.decode(late) is None and fresh.unusable == 1


def test_a_delta_beyond_its_keyframe_is_refused() -> None:
    dec = PoseDecoder()
    dec.decode(_msg(0, _walk(1)[0]))
    bad = PoseDeltas(robot=1, round=1, base=0, index=np.array([len(KEYS)], np.int32),
                     deltas=np.zeros((1, 6), np.float32))
    with pytest.raises(MessageError, match="PoseDeltas.index"):
        dec.decode(bad)


def test_fuzzed_deltas_are_refused_and_counted_never_crash() -> None:
    enc = PoseEncoder(P)
    walk = _walk(5, seed=3)
    first = enc.encode(_msg(0, walk[0]))
    deltas = [m for r in range(1, 5) if isinstance(m := enc.encode(_msg(r, walk[r])), PoseDeltas)]
    assert isinstance(first, PublicPoses) and deltas
    codec = Codec("t0", 1, range(3))
    seeds = [codec.encode(m) for m in deltas]
    rng = np.random.default_rng(11)
    refused = {"codec": 0, "stream": 0, "unusable": 0}
    whole = 0
    for i in range(3000):
        b = bytearray(seeds[i % len(seeds)])
        for _ in range(int(rng.integers(1, 4))):
            j = int(rng.integers(len(b)))
            b[j] = int(rng.integers(256)) if rng.integers(2) else b[j] ^ (1 << int(rng.integers(8)))
        try:
            msg = Codec("t0", 2, range(3)).decode(bytes(b)).msg
        except MessageError:
            refused["codec"] += 1
            continue
        dec = PoseDecoder()
        dec.decode(first)
        try:
            got = dec.decode(msg)
        except MessageError:
            refused["stream"] += 1
            continue
        if got is None:
            refused["unusable"] += 1
            continue
        assert got.poses.shape == (len(KEYS), 4, 4) and np.isfinite(got.poses).all()
        whole += 1
    assert refused["codec"] > 0 and refused["stream"] + refused["unusable"] > 0 and whole > 0


@pytest.mark.parametrize("drop", [0.0, 0.1])
def test_the_stream_reaches_the_same_optimum_for_fewer_bytes(pgo_data: Path, drop: float) -> None:
    """Distributed PGO with full public poses and with the stream, against the centralised optimum."""
    kw = dict(robots=4, max_rounds=300, drop=drop, seed=3) if drop else dict(robots=5, max_rounds=300)
    full = run_pgo([pgo_data / "smallGrid3D.g2o"], **kw)  # type: ignore[arg-type]
    stream = run_pgo([pgo_data / "smallGrid3D.g2o"], stream=P, **kw)  # type: ignore[arg-type]
    assert abs(full.relative_gap) <= 1e-4 and abs(stream.relative_gap) <= 1e-4
    if not drop:  # no loss: the very same optimum, as fast
        assert abs(stream.relative_gap - full.relative_gap) <= 1e-9 and stream.rounds <= full.rounds + 2
    full_bytes = full.bytes_by_topic["pgo/public_poses"]
    stream_bytes = stream.bytes_by_topic["pgo/public_poses"] + stream.bytes_by_topic.get("pgo/pose_deltas", 0)
    assert stream.bytes_by_topic["pgo/pose_deltas"] > 0 and stream_bytes * 2 < full_bytes
