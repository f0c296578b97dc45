"""The checkpoint file: exact round trip of an Agent's state, and every kind of bad file refused."""

import itertools
import struct
import zlib
from collections import Counter

import gtsam
import msgpack
import numpy as np
import pytest

from kimera_multi_py.agent.agent import Agent
from kimera_multi_py.agent.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    MAGIC,
    OBJECT,
    checkpoint_bytes,
    load_checkpoint,
    save_checkpoint,
    snapshot,
)
from kimera_multi_py.agent.params import AgentParams
from kimera_multi_py.core.errors import CheckpointError, KimeraMultiError
from kimera_multi_py.frontend.pcm import PcmNoise
from kimera_multi_py.mapping.config import MappingConfig, ObjectMapConfig
from kimera_multi_py.sim import load_scenario
from kimera_multi_py.sim.source import SimSource

from ..sim.helpers import TINY

HEADER = "<IIQQQI"  # version, flags, tree length, raw body length, stored body length, CRC
HEAD = len(MAGIC) + struct.calcsize(HEADER)


def state_equal(a: object, b: object, path: str = "agent", atol: float = 0.0) -> None:
    """Recursive equality of two object graphs, written independently of the checkpoint codec;
    floating-point values within ``atol``, relative and absolute (another machine rounds differently)."""
    assert type(a) is type(b), f"{path}: {type(a)} vs {type(b)}"
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        if atol and a.dtype.kind in "fc":
            assert np.allclose(a, b, rtol=atol, atol=atol, equal_nan=True), path
        else:
            assert np.array_equal(a, b, equal_nan=True), path
    elif atol and isinstance(a, float | np.floating):
        assert abs(a - b) <= atol * (1.0 + abs(b)) or (a != a and b != b), f"{path}: {a!r} vs {b!r}"  # type: ignore[operator]
    elif isinstance(a, np.generic | int | float | str | bytes | bool | type(None)):
        assert a == b or (a != a and b != b), f"{path}: {a!r} vs {b!r}"
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            state_equal(x, y, f"{path}[{i}]", atol)
    elif isinstance(a, set | frozenset):
        assert a == b, path
    elif isinstance(a, dict):
        assert list(a) == list(b), f"{path}: keys"
        for k in a:
            state_equal(a[k], b[k], f"{path}[{k!r}]", atol)
    elif hasattr(a, "model_dump"):
        assert a == b, path
    else:
        slots = [s for c in type(a).__mro__ for s in c.__dict__.get("__slots__", ())]
        da = {**getattr(a, "__dict__", {}), **{s: getattr(a, s) for s in slots if hasattr(a, s)}}
        db = {**getattr(b, "__dict__", {}), **{s: getattr(b, s) for s in slots if hasattr(b, s)}}
        assert sorted(da) == sorted(db), f"{path}: attributes {sorted(set(da) ^ set(db))}"
        for k in da:
            state_equal(da[k], db[k], f"{path}.{k}", atol)


@pytest.fixture(scope="module")
def agent():
    params = AgentParams(mapping=MappingConfig(keyframes_per_submap=5, objects=ObjectMapConfig(min_points=6)),
                         pcm=PcmNoise(0.05, 0.1, 0.01, 0.02), odom_sigmas=(np.float64(0.01), 0.02))
    a = Agent(0, (0, 1), params)
    for kf in itertools.islice(SimSource(load_scenario(TINY), 0, 0), 30):
        a.process_keyframe(kf)
    assert a.objects.landmarks and len(a.map.submaps) == 6
    return a


@pytest.fixture(scope="module")
def ckpt(agent, tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "agent.ckpt"
    save_checkpoint(path, agent, {"next": 30})
    return path


def test_round_trip_restores_every_attribute(agent, tmp_path):
    x = np.arange(6, dtype=np.float32).reshape(2, 3)
    extra = {"next": 30, (1, 2): {3, 4}, 5: [x, x, np.int16(7), np.float64(0.5)], "t": (None, True, b"\x00"),
             "big": 2**63 + 1, "f": frozenset({"a"}), "errors": Counter({"query": 2}), "nan": float("nan")}
    for compress in (True, False):
        path = tmp_path / f"a{compress}.ckpt"
        save_checkpoint(path, agent, extra, compress=compress)
        restored, got = load_checkpoint(path)
        state_equal(agent, restored)
        state_equal(extra, got, "extra")
        assert got[5][0] is got[5][1]  # shared arrays stay shared
        assert type(restored.params.odom_sigmas[0]) is np.float64 and restored.params == agent.params
        assert checkpoint_bytes(restored, got, compress) == path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["aFalse.ckpt", "aTrue.ckpt"]  # no temporary files


def _split(data: bytes) -> tuple[bytes, bytes]:
    """(msgpack tree, array section) of a checkpoint file."""
    _, flags, tree_len, _, _, _ = struct.unpack_from(HEADER, data, len(MAGIC))
    body = zlib.decompress(data[HEAD:]) if flags else data[HEAD:]
    return body[:tree_len], body[tree_len:]


def _join(tree: bytes, arrays: bytes, version: int = FORMAT_VERSION) -> bytes:
    """An uncompressed checkpoint file with a valid CRC."""
    body = tree + arrays
    return MAGIC + struct.pack(HEADER, version, 0, len(tree), len(body), len(body), zlib.crc32(body)) + body


def _rewrite(data: bytes, version: int | None = None, doc=None) -> bytes:
    """A checkpoint with a changed header version or tree, and a valid CRC."""
    tree, arrays = _split(data)
    if doc is not None:
        tree = msgpack.packb(doc(msgpack.unpackb(tree, strict_map_key=False)), use_bin_type=True)
    return _join(tree, arrays, FORMAT_VERSION if version is None else version)


def _foreign_class(doc):
    assert doc["agent"][0] == OBJECT
    doc["agent"][2] = "os.system"
    return doc


BAD_FILES = {
    "version": (lambda d: _rewrite(d, version=FORMAT_VERSION + 1), f"format version {FORMAT_VERSION + 1}"),
    "truncated": (lambda d: d[: len(d) // 2], "truncated checkpoint payload"),
    "truncated header": (lambda d: d[:12], "truncated checkpoint (incomplete header)"),
    "empty": (lambda d: b"", "bad magic"),
    "garbage": (lambda d: np.random.default_rng(0).bytes(4096), "bad magic"),
    "garbage after magic": (lambda d: MAGIC + np.random.default_rng(1).bytes(4096), "format version"),
    "pickle": (lambda d: b"\x80\x05\x95garbage", "bad magic"),
    "bit flip": (lambda d: d[:-100] + bytes([d[-100] ^ 1]) + d[-99:], "CRC mismatch"),
    "trailing bytes": (lambda d: d + b"x", "trailing bytes"),
    "class outside the allowlist": (lambda d: _rewrite(d, doc=_foreign_class), "'os.system' is not on the"),
    "foreign payload": (lambda d: _rewrite(d, doc=lambda doc: {**doc, "format": "other"}), f"not a {FORMAT}"),
    "not an agent": (lambda d: _rewrite(d, doc=lambda doc: {**doc, "agent": 3}), "does not hold an Agent"),
    "bad array": (lambda d: _rewrite(d, doc=lambda doc: {**doc, "extra": [5, 0, "|O", [1], 0]}),
                  "dtype '|O' is not allowed"),
    "array past the end": (lambda d: _rewrite(d, doc=lambda doc: {**doc, "extra": [5, 0, "<f8", [2**40], 0]}),
                           "array data outside the file"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_files_raise_one_line_naming_the_file(ckpt, tmp_path, case):
    make, problem = BAD_FILES[case]
    path = tmp_path / "bad.ckpt"
    path.write_bytes(make(ckpt.read_bytes()))
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path)
    msg = str(err.value)
    assert msg.startswith(f"{path}: ") and problem in msg and "\n" not in msg, msg
    assert isinstance(err.value, KimeraMultiError)


def test_missing_file(tmp_path):
    with pytest.raises(CheckpointError, match="cannot read checkpoint"):
        load_checkpoint(tmp_path / "none.ckpt")


def test_save_refuses_state_it_cannot_write_and_keeps_the_old_file(agent, ckpt, tmp_path):
    path = tmp_path / "a.ckpt"
    save_checkpoint(path, agent, {"next": 1})
    old = path.read_bytes()
    cases = [("pgo_values", gtsam.Values(), "agent.pgo_values: type gtsam"),
             ("callback", lambda: None, "agent.callback: type builtins.function is not allowed"),
             ("labels", np.array(["a"], dtype=object), "agent.labels: array of dtype object")]
    for name, value, problem in cases:
        setattr(agent, name, value)
        try:
            with pytest.raises(CheckpointError, match=problem):
                save_checkpoint(path, agent)
        finally:
            delattr(agent, name)
    with pytest.raises(CheckpointError, match="extra.*Agent is not allowed"):
        save_checkpoint(path, agent, {"nested": agent})
    assert path.read_bytes() == old and sorted(p.name for p in tmp_path.iterdir()) == ["a.ckpt"]


def test_state_of_equal_agents_is_equal_bytes(agent, ckpt):
    restored, extra = load_checkpoint(ckpt)
    assert checkpoint_bytes(restored, extra) == checkpoint_bytes(agent, {"next": 30}) == ckpt.read_bytes()


def test_a_snapshot_is_detached_from_the_agent(tmp_path):
    a = Agent(1, (0, 1))
    for kf in itertools.islice(SimSource(load_scenario(TINY), 0, 1), 3):
        a.process_keyframe(kf)
    before = checkpoint_bytes(a)
    snap = snapshot(a, copy=True)
    a.poses[0][0, 3] += 1.0  # the agent goes on changing its arrays in place
    a.map._fused.blocks[next(iter(a.map._fused.blocks))][1][0] += 1
    snap.write(tmp_path / "s.ckpt")
    assert (tmp_path / "s.ckpt").read_bytes() == before


def test_fuzzed_payloads_with_a_valid_crc_load_or_raise_checkpoint_error(tmp_path):
    """Mutations past the CRC reach the msgpack and state decoders: only CheckpointError may escape."""
    a = Agent(1, (0, 1))
    for kf in itertools.islice(SimSource(load_scenario(TINY), 0, 1), 3):
        a.process_keyframe(kf)
    tree, arrays = _split(checkpoint_bytes(a, {"k": [1, (2, 3)]}, compress=False))
    rng = np.random.default_rng(0)
    outcomes = {"loaded": 0, "refused": 0}
    path = tmp_path / "f.ckpt"
    for _ in range(300):
        t = bytearray(tree)
        for i in rng.integers(0, len(t), size=rng.integers(1, 4)):
            t[i] = int(rng.integers(0, 256))
        if rng.random() < 0.1:
            t = t[: int(rng.integers(0, len(t)))]
        path.write_bytes(_join(bytes(t), arrays))
        try:
            load_checkpoint(path)
            outcomes["loaded"] += 1
        except CheckpointError as exc:
            assert str(exc).startswith(f"{path}: ")
            outcomes["refused"] += 1
    assert outcomes["refused"] > 50, outcomes


def test_checkpoint_written_before_the_package_split_loads():
    """``tests/data/agent_tiny_v6.kmc`` was written by the code before the package was split by
    concern (classes under ``consensus/``): it loads through the renamed-class table and holds
    the same state as an agent that processes the same 12 keyframes now."""
    from pathlib import Path

    from kimera_multi_py.team.build import agent_params

    old, extra = load_checkpoint(Path(__file__).parents[1] / "data" / "agent_tiny_v6.kmc")
    cfg = load_scenario(TINY)
    fresh = Agent(0, (0, 1), agent_params(cfg))
    for kf in itertools.islice(SimSource(cfg, 0, 0), 12):
        fresh.process_keyframe(kf)
    assert extra == {"next": 12}
    old.scan_odometry.stats.seconds = fresh.scan_odometry.stats.seconds  # wall times, not state
    old.front_end_seconds = fresh.front_end_seconds
    # version 6 tracked no people: the loaded agent has an empty tracker that knows its submaps
    assert old.people.log == [] and sorted(old.people._ref) == sorted(fresh.people._ref)
    old.people = fresh.people
    # the map's tree is a view of its evidence, brought up to date when read: equal leaves
    for name in ("codes", "levels", "values"):
        assert np.array_equal(getattr(old.map.octree, name), getattr(fresh.map.octree, name)), name
    old.map._tree = fresh.map._tree
    state_equal(old, fresh, atol=1e-9)  # the file was written on another machine
