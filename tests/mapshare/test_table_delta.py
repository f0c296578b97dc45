"""Row deltas of object and people tables: the receiver rebuilds the sender's table bit for bit,
a delta it cannot place is refused and counted, and corrupt deltas never crash."""

import dataclasses

import numpy as np
import pytest

from kimera_multi_py.comms.codec import Codec
from kimera_multi_py.core.errors import MessageError
from kimera_multi_py.core.geometry import make_pose
from kimera_multi_py.mapshare.table_delta import TableHistory, delta_rows, expand_rows

from ..consensus.test_object_exchange import Robot, run
from ..mapping.helpers import CHAIR, TABLE
from ..mapping.test_objects import box_points

ROWS = ("ids", "centres", "labels")


def table(rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
    return {"ids": rng.permutation(10 * n)[:n].astype(np.int64), "centres": rng.normal(size=(n, 3)),
            "labels": rng.integers(0, 5, n).astype(np.int32)}


@pytest.mark.parametrize("seed", range(20))
def test_a_table_expands_from_its_delta_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    base = table(rng, int(rng.integers(0, 40)))
    n = len(base["ids"])
    # the next version: some rows kept, some changed, some gone, some new, in a new order
    keep = rng.random(n) < 0.7
    new = {k: v[keep] for k, v in base.items()}
    changed = rng.random(len(new["ids"])) < 0.2
    new["centres"] = new["centres"] + changed[:, None] * 0.01
    extra = table(rng, int(rng.integers(0, 5)))
    new = {k: np.concatenate([new[k], extra[k]]) for k in ROWS}
    same = np.concatenate([~changed, np.zeros(len(extra["ids"]), bool)])  # rows of the base, unchanged
    order = rng.permutation(len(new["ids"]))
    new, same = {k: v[order] for k, v in new.items()}, same[order]

    reuse, fresh = delta_rows([base[k] for k in ROWS], [new[k] for k in ROWS])
    assert np.array_equal(fresh, np.flatnonzero(reuse < 0))
    assert np.all(reuse[same] >= 0)
    out = expand_rows("T", base, {k: new[k][fresh] for k in ROWS}, reuse)
    for k in ROWS:
        assert out[k].dtype == new[k].dtype and out[k].tobytes() == new[k].tobytes()


def test_unchanged_rows_are_reused_and_only_changed_ones_travel() -> None:
    rng = np.random.default_rng(1)
    base = table(rng, 30)
    new = {k: v.copy() for k, v in base.items()}
    new["centres"][[3, 17]] += 0.5
    reuse, fresh = delta_rows([base[k] for k in ROWS], [new[k] for k in ROWS])
    assert fresh.tolist() == [3, 17]
    assert np.array_equal(reuse[reuse >= 0], np.delete(np.arange(30), [3, 17]))


@pytest.mark.parametrize("seed", range(30))
def test_a_corrupt_delta_is_refused_or_consistent_never_a_crash(seed: int) -> None:
    rng = np.random.default_rng(seed)
    base = table(rng, 12)
    reuse = rng.integers(-3, 16, int(rng.integers(0, 20))).astype(np.int32)
    n_fresh = int((reuse == -1).sum()) + int(rng.integers(-1, 2))
    fresh = table(rng, max(n_fresh, 0))
    try:
        out = expand_rows("T", base, fresh, reuse)
    except MessageError:
        return
    assert all(len(v) == len(reuse) for v in out.values())


def test_the_history_keeps_the_newest_versions() -> None:
    h = TableHistory(keep=2)
    for v in (1, 2, 3):
        h.add(0, v, f"t{v}")
    assert (h.get(0, 1), h.get(0, 2), h.get(0, 3)) == (None, "t2", "t3")
    h.forget(0)
    assert h.get(0, 3) is None


def _see_more(r: Robot, x: float, y: float, seed: int) -> None:
    """More scans of one of the robot's objects: its row of the table changes, the others do not."""
    pts = box_points([x, y, 0.45], [0.5, 0.5, 0.9], 40, np.random.default_rng(seed))
    r.om.update(pts, np.full(len(pts), CHAIR), 0)


OBJECTS = [((1.0, 1.0), CHAIR), ((3.0, 1.0), TABLE), ((5.0, 1.0), CHAIR), ((7.0, 2.0), TABLE)]


def test_a_changed_object_table_travels_as_a_delta_and_arrives_whole() -> None:
    a, b = Robot(0, OBJECTS, np.eye(4), 0), Robot(1, [((1.0, 6.0), CHAIR)], np.eye(4), 1)
    sent: list = []
    t = run([a, b], {(0, 1)}, 3)
    codec = Codec("t0", 0)
    for k in range(6):
        _see_more(a, 1.0, 1.0, 10 + k)  # robot 0 keeps seeing its first chair
        out = a.ex.step(t)
        sent += [(m, a.ex.history.get(0, m.version)) for m in out if m.source == 0]
        for m in out:
            b.ex.handle(m)
        for m in b.ex.step(t):
            a.ex.handle(m)
        t += 1.0
        assert a.ex._content(b.ex.tables[0]) == a.ex._content(a.ex.tables[0])  # bit for bit, every period
        assert b.ex.tables[0].version == a.ex.tables[0].version
    deltas = [(m, whole) for m, whole in sent if m.base]
    assert deltas, "robot 0's changed tables went whole"
    for m, whole in deltas:
        assert len(m.reuse) == len(OBJECTS) and (m.reuse < 0).sum() == len(m.ids) < len(OBJECTS)
        assert len(codec.encode(m)) < len(codec.encode(dataclasses.replace(whole, held_sources=m.held_sources,
                                                                            held_versions=m.held_versions)))
    assert b.ex.team_objects() == a.ex.team_objects()


def test_a_delta_whose_base_the_receiver_lacks_is_counted_and_the_refresh_repairs_it() -> None:
    a, b = Robot(0, OBJECTS, np.eye(4), 0), Robot(1, [((1.0, 6.0), CHAIR)], np.eye(4), 1)
    t = run([a, b], {(0, 1)}, 3)
    b.ex.history.forget(0)  # robot 1 lost the versions it held (as after a restart)
    _see_more(a, 5.0, 1.0, 5)
    out = [m for m in a.ex.step(t) if m.source == 0]
    assert out and out[0].base
    for m in out:
        b.ex.handle(m)
    assert b.ex.ignored["objects_no_base"] == 1
    assert b.ex.tables[0].version < a.ex.tables[0].version
    run([a, b], {(0, 1)}, 4, t0=t + 1.0)  # a refresh comes within refresh_every periods
    assert a.ex._content(b.ex.tables[0]) == a.ex._content(a.ex.tables[0])


def test_a_whole_table_that_claims_reused_rows_is_refused() -> None:
    a, b = Robot(0, OBJECTS, np.eye(4), 0), Robot(1, [((1.0, 6.0), CHAIR)], np.eye(4), 1)
    run([a, b], {(0, 1)}, 1)
    b.ex.set_neighbours({0})
    bad = dataclasses.replace(a.ex.tables[0], version=9, reuse=np.zeros(len(OBJECTS), np.int32))
    with pytest.raises(MessageError):
        b.ex.handle(bad)


def test_a_pgo_move_after_deltas_still_moves_every_copy() -> None:
    a, b = Robot(0, OBJECTS, np.eye(4), 0), Robot(1, [((1.0, 6.0), CHAIR)], np.eye(4), 1)
    t = run([a, b], {(0, 1)}, 3)
    _see_more(a, 5.0, 1.0, 7)
    t = run([a, b], {(0, 1)}, 2, t0=t)
    a.move(make_pose(np.eye(3), [0.3, -0.2, 0.0]))
    run([a, b], {(0, 1)}, 4, t0=t)
    assert b.ex.team_objects() == a.ex.team_objects()
