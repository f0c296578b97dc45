"""Packed verification clouds (kimera_multi_py.comms.clouds): round trips, and corrupt bytes refused."""

import numpy as np
import pytest

from kimera_multi_py.comms import compression
from kimera_multi_py.comms.clouds import COMPACT, COMPACT_ZLIB, COMPACT_ZSTD, RAW, pack_cloud, unpack_cloud
from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.comms.messages.closures import LoopClosureReply
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.semantics import CLASS_NAMES

FORMATS = [RAW, COMPACT_ZLIB] + ([COMPACT_ZSTD] if compression.DEFAULT == compression.ZSTD else [])


def _cloud(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.uniform(-15, 15, (n, 3)), rng.integers(0, len(CLASS_NAMES), n)


def test_the_class_vocabulary_fits_a_uint8() -> None:
    assert len(CLASS_NAMES) <= 256


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.parametrize("n", [0, 1, 777])
def test_round_trip(fmt: int, n: int) -> None:
    xyz, labels = _cloud(n)
    got, got_labels = unpack_cloud(pack_cloud(xyz, labels, fmt), n)
    assert got.shape == (n, 3) and got.dtype == np.float32 and np.array_equal(got_labels, labels)
    # float16 keeps 11 significant bits: within 2^-11 of the value (relative), i.e. 8 mm at 16 m
    tol = 1e-6 if fmt == RAW else 2.0**-11
    assert np.all(np.abs(got - xyz) <= tol * np.maximum(np.abs(xyz), 2.0**-14) + 1e-7)


def test_compact_is_smaller_than_raw_and_refuses_what_it_cannot_hold() -> None:
    xyz, labels = _cloud(500)
    order = np.lexsort(np.floor(xyz / 0.2).T[::-1])  # voxel order, as the agent sends them
    assert pack_cloud(xyz[order], labels[order], COMPACT).nbytes < 0.5 * pack_cloud(xyz, labels, RAW).nbytes
    with pytest.raises(ValueError, match="uint8"):
        pack_cloud(xyz[:2], [0, 256])
    with pytest.raises(ValueError, match="float16"):
        pack_cloud([[7e4, 0.0, 0.0]], [1])
    with pytest.raises(ValueError, match="labels"):
        pack_cloud(xyz[:3], labels[:2])


@pytest.mark.parametrize("fmt", FORMATS)
def test_wrong_counts_and_formats_are_refused(fmt: int) -> None:
    blob = pack_cloud(*_cloud(50), fmt)
    for n in (49, 51, 0, -1):
        with pytest.raises(MessageError, match="cloud"):
            unpack_cloud(blob, n)
    bad = blob.copy()
    bad[0] = 9
    with pytest.raises(MessageError, match="unknown format"):
        unpack_cloud(bad, 50)
    with pytest.raises(MessageError, match="empty"):
        unpack_cloud(np.zeros(0, np.uint8), 0)


def _reply(fmt: int, n: int = 300) -> LoopClosureReply:
    xyz, labels = _cloud(n, seed=1)
    return LoopClosureReply(robot=1, request_id=4, keyframe=12, found=True, pose=np.eye(4), num_points=n,
                            cloud=pack_cloud(xyz, labels, fmt), object_centroids=np.zeros((2, 3), np.float32),
                            object_classes=np.array([3, 4], np.int32))


@pytest.mark.parametrize("fmt", FORMATS)
def test_fuzzed_replies_are_refused_and_counted_never_crash(fmt: int) -> None:
    """Byte mutations of encoded replies: the codec or the cloud refuses (MessageError, counted),
    or the reply is whole (every point finite, as many as it says)."""
    codec = Codec("t0", 1, range(3))
    data = codec.encode(_reply(fmt))
    body_at = data.find(bytes(_reply(fmt).cloud[:8]))
    assert body_at > 0
    rng = np.random.default_rng(fmt)
    refused = {"codec": 0, "cloud": 0}
    whole = 0
    for i in range(3000):
        b = bytearray(data)
        # mostly inside the packed cloud (the codec checks the rest), sometimes anywhere
        lo = body_at if i % 4 else 0
        for _ in range(int(rng.integers(1, 4))):
            j = int(rng.integers(lo, len(b)))
            if rng.integers(2):
                b[j] ^= 1 << int(rng.integers(8))
            else:
                b[j] = int(rng.integers(256))
        try:
            msg = Codec("t0", 2, range(3)).decode(bytes(b)).msg
        except MessageError:
            refused["codec"] += 1
            continue
        assert isinstance(msg, LoopClosureReply)
        try:
            xyz, labels = msg.points()
        except MessageError:
            refused["cloud"] += 1
            continue
        assert xyz.shape == (msg.num_points, 3) and len(labels) == msg.num_points and np.isfinite(xyz).all()
        whole += 1
    assert refused["cloud"] > 100 and refused["codec"] > 0 and whole > 0
    assert sum(refused.values()) + whole == 3000
