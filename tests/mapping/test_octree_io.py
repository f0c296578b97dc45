import json
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from kimera_multi_py.core.errors import MapError
from kimera_multi_py.mapping import SemanticOctree
from kimera_multi_py.mapping.octree_io import (
    FORMAT_VERSION,
    MAGIC,
    export_bt,
    export_ply,
    load_octree,
    octree_from_bytes,
    octree_to_bytes,
    save_octree,
)

from .helpers import HUMAN, K, room_scan

ORIGINS = [np.array([0.0, 0.0, 1.0]), np.array([-1.5, 1.0, 1.2]), np.array([1.0, -1.2, 0.9])]


@pytest.fixture(scope="module")
def tree():
    t = SemanticOctree(0.1, K, dynamic_classes=[HUMAN], top_k=4, h_min=-4.0)
    for i in range(6):
        o = ORIGINS[i % 3]
        p, lab = room_scan(o, 3000, seed=i, noise=0.1)
        t.insert_scan(o, p, lab)
    return t


@pytest.fixture(scope="module")
def blob(tree):
    return octree_to_bytes(tree)


@pytest.fixture(scope="module")
def blob_holder(blob):
    """The file inside a list, so that hypothesis does not print 200 kB on failure."""
    return [blob]


def test_save_load_round_trip_is_exact(tree, tmp_path):
    path = tmp_path / "map.kmo"
    save_octree(tree, path)
    back = load_octree(path)
    assert np.array_equal(back.codes, tree.codes)
    assert np.array_equal(back.levels, tree.levels)
    assert np.array_equal(back.values, tree.values)
    assert back.resolution == tree.resolution and back.num_classes == K
    assert back.dynamic_classes == (HUMAN,) and back.top_k == 4
    assert back.model.params() == tree.model.params()
    assert len(path.read_bytes()) < tree.nbytes  # compressed
    empty = octree_from_bytes(octree_to_bytes(SemanticOctree(0.2, 3)))
    assert empty.num_leaves == 0 and empty.resolution == 0.2


def test_every_truncation_raises_map_error(blob):
    cuts = list(range(0, 300)) + list(range(300, len(blob), max(1, len(blob) // 500)))
    for n in cuts:
        with pytest.raises(MapError):
            octree_from_bytes(blob[:n])


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_fuzzed_files_raise_map_error_only(blob_holder, data):
    blob = blob_holder[0]
    mode = data.draw(st.sampled_from(["flip", "splice", "garbage"]))
    b = bytearray(blob)
    if mode == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(b) - 1))
            b[i] ^= data.draw(st.integers(1, 255))
    elif mode == "splice":
        i = data.draw(st.integers(0, len(b)))
        b[i:i] = data.draw(st.binary(min_size=1, max_size=64))
    else:
        b = bytearray(data.draw(st.binary(max_size=2000)))
        if data.draw(st.booleans()):
            b[:8] = MAGIC
    assume(bytes(b) != blob)
    with pytest.raises(MapError):
        octree_from_bytes(bytes(b))


def _forge(header: dict, raw: bytes, version: int = FORMAT_VERSION) -> bytes:
    """A file with a valid checksum around arbitrary content."""
    h = json.dumps(header).encode()
    payload = zlib.compress(raw)
    body = (
        struct.pack("<8sHI", MAGIC, version, len(h)) + h + struct.pack("<Q", len(payload)) + payload
    )
    return body + struct.pack("<I", zlib.crc32(body))


def _parts(blob):
    hlen = struct.unpack_from("<I", blob, 10)[0]
    header = json.loads(blob[14 : 14 + hlen])
    plen = struct.unpack_from("<Q", blob, 14 + hlen)[0]
    raw = zlib.decompress(blob[22 + hlen : 22 + hlen + plen])
    return header, raw


def test_checksummed_but_inconsistent_files_raise_map_error(tree, blob):
    header, raw = _parts(blob)
    assert octree_from_bytes(_forge(header, raw)).num_leaves == tree.num_leaves
    n, k1 = tree.num_leaves, K + 1
    with pytest.raises(MapError, match="version"):
        octree_from_bytes(_forge(header, raw, version=FORMAT_VERSION + 1))
    with pytest.raises(MapError):
        octree_from_bytes(_forge({**header, "num_leaves": n + 1}, raw))
    with pytest.raises(MapError):
        octree_from_bytes(_forge({**header, "resolution": -1.0}, raw))
    with pytest.raises(MapError):
        octree_from_bytes(_forge({k: v for k, v in header.items() if k != "model"}, raw))
    with pytest.raises(MapError):
        octree_from_bytes(_forge({**header, "top_k": "three"}, raw))
    for key in ("hit", "psi", "h_max"):  # JSON accepts NaN; the model must not
        with pytest.raises(MapError, match="non-finite"):
            octree_from_bytes(
                _forge({**header, "model": {**header["model"], key: float("nan")}}, raw)
            )
    codes = np.frombuffer(raw, "<i8", n).copy()
    codes[5] = 0  # deltas no longer increasing: unsorted / overlapping leaves
    with pytest.raises(MapError, match="unsorted|overlapping|aligned"):
        octree_from_bytes(_forge(header, codes.tobytes() + raw[8 * n :]))
    levels = np.frombuffer(raw, "<i1", n, 8 * n).copy()
    levels[np.argmax(levels == 0)] = 20
    with pytest.raises(MapError, match="level"):
        octree_from_bytes(_forge(header, raw[: 8 * n] + levels.tobytes() + raw[9 * n :]))
    values = np.frombuffer(raw, "<i2", offset=9 * n).reshape(n, k1).copy()
    values[0, 3] = 32000
    with pytest.raises(MapError, match="clamping"):
        octree_from_bytes(_forge(header, raw[: 9 * n] + values.tobytes()))
    with pytest.raises(MapError):
        octree_from_bytes(_forge(header, b"\x00" * 17))
    with pytest.raises(MapError):
        octree_from_bytes(b"{}" + blob[2:])


JSON_VALUES = [None, True, -1, 0, 1, 3, 2**31, 10**400, -1e308, 0.05, 1e-300, float("nan"), float("inf"), "x",
               [], [1, 2], [-1], [99], {}, {"hit": 1.0}]


def _mutate_raw(raw: bytes, n: int, k1: int, rng: np.random.Generator) -> bytes:
    """The decompressed payload with a few entries of one section changed (or cut / padded)."""
    sections = {"codes": (0, 8 * n, "<i8"), "levels": (8 * n, 9 * n, "<i1"), "values": (9 * n, len(raw), "<i2")}
    what = rng.choice([*sections, "bytes", "length"])
    if what == "length":
        cut = int(rng.integers(0, len(raw)))
        return raw[:cut] if rng.random() < 0.5 else raw + rng.bytes(cut % 64 + 1)
    if what == "bytes":
        b = bytearray(raw)
        for i in rng.integers(0, len(b), size=rng.integers(1, 6)):
            b[i] ^= int(rng.integers(1, 256))
        return bytes(b)
    start, stop, dt = sections[what]
    arr = np.frombuffer(raw[start:stop], dt).copy()
    info = np.iinfo(arr.dtype)
    idx = rng.integers(0, len(arr), size=rng.integers(1, 4))
    arr[idx] = rng.choice([info.min, info.max, -1, 0, 1, 2, 8, int(rng.integers(info.min, info.max))], len(idx))
    return raw[:start] + arr.astype(dt).tobytes() + raw[stop:]


def _mutate_header(header: dict, rng: np.random.Generator) -> dict:
    """The header with one field (or one model parameter) replaced by an arbitrary JSON value, or dropped."""
    h = json.loads(json.dumps(header))
    target = h["model"] if rng.random() < 0.3 else h
    key = str(rng.choice(sorted(target)))
    if rng.random() < 0.15:
        del target[key]
    else:
        target[key] = JSON_VALUES[int(rng.integers(len(JSON_VALUES)))]
    return h


def test_fuzzed_contents_with_a_valid_checksum_raise_map_error_only():
    """Mutations behind a recomputed CRC (and, for the payload, a recomputed zlib stream) reach the
    header and structure checks: every file either raises MapError or loads a consistent octree."""
    tree = SemanticOctree(0.1, K, dynamic_classes=[HUMAN], top_k=4, h_min=-4.0)
    p, lab = room_scan(ORIGINS[0], 400, seed=0, noise=0.1)
    tree.insert_scan(ORIGINS[0], p, lab)
    header, raw = _parts(octree_to_bytes(tree))
    n, k1 = tree.num_leaves, K + 1
    rng = np.random.default_rng(0)
    messages: set[str] = set()
    loaded = 0
    for trial in range(400):
        h, r = header, raw
        if trial % 3 != 1:
            r = _mutate_raw(raw, n, k1, rng)
        if trial % 3 != 0:
            h = _mutate_header(header, rng)
        try:
            back = octree_from_bytes(_forge(h, r))
        except MapError as exc:
            messages.add(str(exc).split(": ", 1)[1].split(" (")[0])
            continue
        loaded += 1  # a mutation the format cannot tell from real data: the tree must be whole
        again = octree_from_bytes(octree_to_bytes(back))
        assert np.array_equal(again.codes, back.codes) and np.array_equal(again.values, back.values)
        assert np.all(np.diff(back.codes) > 0) and back.values[:, 0].max(initial=0) == 0
    # the structural checks themselves were reached, not just the CRC
    for needle in ("unsorted or overlapping", "not aligned", "level out of range", "clamping range",
                   "payload holds", "missing or of the wrong type", "bad parameters"):
        assert any(needle in m for m in messages), (needle, sorted(messages))
    assert loaded < 100, loaded


def test_missing_file_raises_map_error(tmp_path):
    with pytest.raises(MapError):
        load_octree(tmp_path / "nope.kmo")


def test_export_ply(tree, tmp_path):
    path = tmp_path / "map.ply"
    n = export_ply(tree, path)
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    assert f"element vertex {n}".encode() in head
    rec = np.frombuffer(
        body,
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
            ("label", "<u2"),
            ("size", "<f4"),
        ],
    )
    occ = tree.occupied_leaves()
    assert len(rec) == n == occ.sum()
    assert np.array_equal(rec["label"], np.argmax(tree.values[occ], axis=1))
    centers = np.stack([rec["x"], rec["y"], rec["z"]], 1)
    assert np.array_equal(tree.find(centers), np.flatnonzero(occ))


def test_export_bt_reads_back_in_octomap(tree, tmp_path):
    import pyoctomap

    path = tmp_path / "map.bt"
    size = export_bt(tree, path)
    assert size == tree.num_nodes
    ot = pyoctomap.OcTree(0.1)
    assert ot.readBinary(str(path))
    assert ot.size() == tree.num_nodes
    assert ot.getNumLeafNodes() == tree.num_leaves
    ours = {}
    lv = tree.leaves()
    for c, s, occ in zip(np.round(lv.centers, 3), lv.sizes, tree.occupied_leaves(), strict=True):
        ours[(round(float(s), 3), *c.tolist())] = bool(occ)
    seen = 0
    for leaf in ot.begin_leafs():
        key = (round(leaf.getSize(), 3), *np.round(np.array(leaf.getCoordinate()), 3).tolist())
        assert ours[key] == ot.isNodeOccupied(leaf)
        seen += 1
    assert seen == tree.num_leaves
    empty = SemanticOctree(0.1, K)
    assert export_bt(empty, tmp_path / "empty.bt") == 0
    assert pyoctomap.OcTree(0.1).readBinary(str(tmp_path / "empty.bt"))
