"""Keyframe sources: the simulator restarted anywhere, recorded folders, and bad recordings."""

import itertools
import json

import numpy as np
import pytest

from kimera_multi_py.core.errors import ConfigError, DatasetError
from kimera_multi_py.io.sources import RecordedSource, RecordingWriter, read_ground_truth, read_manifest
from kimera_multi_py.sim import Simulation, load_scenario
from kimera_multi_py.sim.scenario import with_team_size
from kimera_multi_py.sim.source import SimSource, keyframe_input, recorded_scenario, write_recording
from kimera_multi_py.team.build import source_from_spec

from ..sim.helpers import TINY

FIELDS = ("index", "stamp", "odometry", "points", "labels", "hit", "max_range")


def assert_same_stream(a, b):
    a, b = list(a), list(b)
    assert len(a) == len(b) and a
    for x, y in zip(a, b, strict=True):
        for f in FIELDS:
            u, v = np.asarray(getattr(x, f)), np.asarray(getattr(y, f))
            assert u.dtype == v.dtype and np.array_equal(u, v), (x.index, f)


@pytest.fixture(scope="module")
def cfg():
    return load_scenario(TINY)


@pytest.fixture(scope="module")
def truth(cfg):
    """The simulator's own streams (Simulation.keyframes), robot -> list of KeyframeInput."""
    sim = Simulation(cfg, 0)
    return {r: [keyframe_input(kf) for kf in sim.keyframes(r)] for r in (0, 1)}


@pytest.fixture(scope="module")
def recording(cfg, tmp_path_factory):
    out = tmp_path_factory.mktemp("rec")
    write_recording(out, cfg, robots=2, seed=0, scenario_path=TINY, chunk_size=16)
    return out


@pytest.mark.parametrize("start", [0, 1, 37, 116, 117])
def test_sim_source_from_any_keyframe_is_the_tail_of_the_full_stream(cfg, truth, start):
    src = SimSource(cfg, 0, 1, start=start)
    assert src.num_keyframes == len(truth[1]) == 117
    got = list(src)
    assert [kf.index for kf in got] == list(range(start, 117))
    if got:
        assert_same_stream(got, truth[1][start:])


def test_sim_source_resumes_from_its_state_and_refuses_a_foreign_one(cfg, truth):
    src = SimSource(cfg, 0, 0)
    for _ in itertools.islice(src, 40):
        pass
    state = json.loads(json.dumps(src.state()))  # plain data: survives JSON (and a checkpoint's extra)
    assert_same_stream(SimSource(cfg, 0, 0, start=40, resume=state), truth[0][40:])
    with pytest.raises(ConfigError, match="resume.*not robot 0, seed 0 at 41"):
        SimSource(cfg, 0, 0, start=41, resume=state)
    with pytest.raises(ConfigError, match="not robot 1"):
        SimSource(cfg, 0, 1, start=40, resume={**state})
    with pytest.raises(ConfigError, match="robot 2 is not in"):
        SimSource(cfg, 0, 2)
    with pytest.raises(ConfigError, match="keyframe 118 is outside"):
        SimSource(cfg, 0, 0, start=118)


def test_a_robots_stream_does_not_depend_on_the_team_size(cfg):
    a = itertools.islice(SimSource(cfg, 3, 1), 5)
    b = itertools.islice(SimSource(with_team_size(cfg, 4), 3, 1), 5)
    assert_same_stream(a, b)


def test_recording_round_trip_equals_the_simulator(recording, truth, cfg):
    manifest = read_manifest(recording)
    assert [e["keyframes"] for e in manifest["robots"]] == [117, 117]
    assert manifest["sensor"]["rows"] == 16 and len(manifest["robots"][0]["chunks"]) == 8
    for r in (0, 1):
        assert_same_stream(RecordedSource(recording, r), truth[r])
        assert_same_stream(RecordedSource(recording, r, start=45), truth[r][45:])  # mid-chunk
        assert_same_stream(RecordedSource(recording, r, start=48), truth[r][48:])  # chunk boundary
    assert list(RecordedSource(recording, 0, start=117)) == []
    gt = read_ground_truth(recording)
    sim = Simulation(cfg, 0)
    for r in (0, 1):
        assert np.array_equal(gt.poses[r], sim.plans[r].poses) and np.array_equal(gt.stamps[r], sim.plans[r].stamps)
    assert gt.info["seed"] == 0 and gt.info["scenario_path"] == str(TINY) and recorded_scenario(gt) == cfg


def test_writer_from_plain_numpy_arrays(tmp_path):
    rng = np.random.default_rng(5)
    written = {0: [], 1: []}
    with RecordingWriter(tmp_path / "mine", sensor={"model": "lidar"}, chunk_size=3) as w:
        for k in range(7):
            for r in (1, 0):  # robots interleave
                n = int(rng.integers(0, 50))
                kf = dict(index=k, stamp=0.5 * k, odometry=np.eye(4) if k == 0 else _yaw(0.1 * r, [0.5, 0, 0]),
                          points=rng.normal(size=(n, 3)).astype(np.float32), labels=rng.integers(0, 5, n),
                          hit=rng.random(n) < 0.7, max_range=10.0)
                w.add_keyframe(r, **kf)
                written[r].append(kf)
    assert not (tmp_path / "mine" / "ground_truth").exists()
    for r in (0, 1):
        got = list(RecordedSource(tmp_path / "mine", r))
        assert [g.index for g in got] == list(range(7))
        for g, kf in zip(got, written[r], strict=True):
            assert np.array_equal(g.points, kf["points"].astype(np.float64)) and g.points.dtype == np.float64
            assert np.array_equal(g.labels, kf["labels"]) and np.array_equal(g.hit, kf["hit"])
            assert np.array_equal(g.odometry, kf["odometry"]) and g.stamp == kf["stamp"] and g.max_range == 10.0
    with pytest.raises(DatasetError, match="ground_truth.*missing"):
        read_ground_truth(tmp_path / "mine")
    with pytest.raises(DatasetError, match="already holds a recording"):
        RecordingWriter(tmp_path / "mine")


def _yaw(a, t):
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = t
    return T


@pytest.mark.parametrize("bad, problem", [
    (dict(index=2), "expected keyframe 1"),
    (dict(odometry=np.full((4, 4), np.nan)), "non-finite odometry"),
    (dict(odometry=np.ones((4, 4))), "not a rigid transform"),
    (dict(points=np.zeros((4, 2))), r"points have shape \(4, 2\)"),
    (dict(labels=np.full(5, 99)), "labels outside"),
    (dict(hit=np.ones(5, dtype=np.int8)), "bool hit mask"),
    (dict(stamp=-1.0), "stamps go backwards"),
    (dict(max_range=np.inf), "max_range"),
    (dict(true_pose=np.full((4, 4), np.nan)), "non-finite true pose"),
])
def test_writer_refuses_bad_keyframes(tmp_path, bad, problem):
    w = RecordingWriter(tmp_path / "r")
    good = dict(index=0, stamp=0.0, odometry=np.eye(4), points=np.zeros((5, 3)), labels=np.zeros(5, int),
                hit=np.zeros(5, bool), max_range=5.0)
    w.add_keyframe(0, **good)
    with pytest.raises(DatasetError, match=problem):
        w.add_keyframe(0, **{**good, "index": 1, **bad})


def _edit_chunk(path, **changes):
    with np.load(path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    for k, f in changes.items():
        if f is None:
            del arrays[k]
        else:
            arrays[k] = f(arrays[k])
    np.savez(path, **arrays)


def _nan_at(a, j=3):
    a = a.copy()
    a[j] = np.nan
    return a


def _manifest(folder, edit):
    path = folder / "manifest.json"
    doc = json.loads(path.read_text())
    edit(doc)
    path.write_text(json.dumps(doc))


CHUNK1 = "robot0/chunk_000001.npz"
BAD_RECORDINGS = {
    "missing manifest": ("manifest.json", lambda d: (d / "manifest.json").unlink(), "missing"),
    "garbage manifest": ("manifest.json", lambda d: (d / "manifest.json").write_bytes(b"\x89\x00garbage"),
                         "unreadable"),
    "foreign manifest": ("manifest.json", lambda d: _manifest(d, lambda m: m.update(format="rosbag")), "not a kimera"),
    "wrong version": ("manifest.json", lambda d: _manifest(d, lambda m: m.update(version=2)), "version 2"),
    "gap in the manifest": ("manifest.json", lambda d: _manifest(d, lambda m: m["robots"][0]["chunks"].pop(1)),
                            "keyframes 16..31 are missing"),
    "wrong count": ("manifest.json", lambda d: _manifest(d, lambda m: m["robots"][0].update(keyframes=200)),
                    "the manifest says 200"),
    "escaping path": ("manifest.json",
                      lambda d: _manifest(d, lambda m: m["robots"][0]["chunks"][0].update(file="../x.npz")),
                      "outside the folder"),
    "missing chunk": (CHUNK1, lambda d: (d / CHUNK1).unlink(), "missing chunk file"),
    "truncated chunk": (CHUNK1, lambda d: (d / CHUNK1).write_bytes((d / CHUNK1).read_bytes()[:5000]),
                        "corrupt or truncated"),
    "garbage chunk": (CHUNK1, lambda d: (d / CHUNK1).write_bytes(np.random.default_rng(0).bytes(3000)),
                      "corrupt or truncated"),
    "pickled chunk": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, index=lambda a: a.astype(object)),
                      "Object arrays cannot be loaded"),
    "gap in a chunk": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, index=lambda a: a + (np.arange(len(a)) >= 5)),
                       "keyframe 21 is missing"),
    "NaN odometry": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, odometry=_nan_at),
                     "non-finite odometry (NaN or inf) at keyframe 19"),
    "NaN stamp": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, stamp=_nan_at), "non-finite stamps"),
    "NaN points": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, points=_nan_at), "non-finite scan points"),
    "short hit mask": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, hit=lambda a: a[:-1]), "must be"),
    "bad offsets": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, offsets=lambda a: a[::-1].copy()),
                    "offsets do not partition"),
    "missing array": (CHUNK1, lambda d: _edit_chunk(d / CHUNK1, labels=None), "missing arrays labels"),
}


@pytest.mark.parametrize("case", sorted(BAD_RECORDINGS))
def test_bad_recordings_raise_dataset_error_naming_the_file(recording, tmp_path, case):
    import shutil

    name, damage, problem = BAD_RECORDINGS[case]
    folder = tmp_path / "rec"
    shutil.copytree(recording, folder)
    damage(folder)
    with pytest.raises(DatasetError) as err:
        list(RecordedSource(folder, 0))
    msg = str(err.value)
    assert str(folder / name) in msg and problem in msg, msg


@pytest.mark.parametrize("damage, problem", [
    (lambda d: (d / "ground_truth" / "poses.npz").write_bytes(b"PK\x03\x04junk"), "corrupt or truncated"),
    (lambda d: _edit_chunk(d / "ground_truth" / "poses.npz", robot1_poses=_nan_at), "non-finite true poses"),
    (lambda d: _edit_chunk(d / "ground_truth" / "poses.npz", robot1_poses=lambda a: a[:-1]), "116 true poses"),
    (lambda d: (d / "ground_truth" / "manifest.json").write_text('{"format": "kimera-multi-ground-truth"}'),
     "version None"),
])
def test_bad_ground_truth(recording, tmp_path, damage, problem):
    import shutil

    folder = tmp_path / "rec"
    shutil.copytree(recording, folder)
    damage(folder)
    with pytest.raises(DatasetError, match=problem) as err:
        read_ground_truth(folder)
    assert str(folder / "ground_truth") in str(err.value)


def test_source_from_spec(recording, cfg, tmp_path):
    s = source_from_spec(f"sim:{TINY}:7", 1, 3)
    assert isinstance(s, SimSource) and s.sim.seed == 7 and s.robot == 1 and next(s).index == 3
    s = source_from_spec(f"sim:{TINY}", 0, 0)
    assert isinstance(s, SimSource) and s.sim.seed == cfg.seed
    s = source_from_spec(f"sim:{TINY}:0", 3, 0)  # a generated robot beyond the file's team
    assert_same_stream(itertools.islice(s, 2), itertools.islice(SimSource(with_team_size(cfg, 5), 0, 3), 2))
    r = source_from_spec(str(recording), 1, 100)
    assert isinstance(r, RecordedSource) and next(r).index == 100
    state = r.state()
    assert [kf.index for kf in source_from_spec(str(recording), 1, 101, resume=state)] == list(range(101, 117))
    with pytest.raises(ConfigError, match="resume"):
        source_from_spec(str(recording), 1, 100, resume=state)
    sim = source_from_spec(f"sim:{TINY}:7", 1, 0)
    for _ in itertools.islice(sim, 20):
        pass
    resumed = source_from_spec(f"sim:{TINY}:7", 1, 20, resume=sim.state())
    assert_same_stream(resumed, sim)
    for bad, problem in [("sim:", "expected sim:SCENARIO"), (str(tmp_path / "nowhere"), "neither"),
                         ("zenoh:foo", "neither")]:
        with pytest.raises(ConfigError, match=problem):
            source_from_spec(bad, 0, 0)
    with pytest.raises(ConfigError, match="file not found"):
        source_from_spec("sim:nowhere.toml:1", 0, 0)
    with pytest.raises(DatasetError, match="manifest.json: missing"):
        source_from_spec(str(tmp_path), 0, 0)  # a folder, but not a recording
    with pytest.raises(DatasetError, match="no robot 5"):
        source_from_spec(str(recording), 5, 0)
