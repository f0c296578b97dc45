"""Person detection and per-robot tracking: crossing people keep their ids, bad detections are
dropped and counted, PGO corrections move the tracks."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from kimera_multi_py.core.geometry import yaw_pose
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.people import PeopleParams, PeopleTracker, PersonDetections, detect_people

HUMAN = CLASS_IDS["human"]
WALL = CLASS_IDS["wall"]


def person_points(centre_xy, sensor_xy, rng, radius=0.25, height=1.75, n=200):
    """The near half of an upright cylinder, as a camera at ``sensor_xy`` sees it."""
    c = np.asarray(centre_xy, float)
    view = np.arctan2(*(np.asarray(sensor_xy, float) - c)[::-1])
    a = view + rng.uniform(-np.pi / 2, np.pi / 2, n)
    z = rng.uniform(0.05, 0.05 + height, n)
    return np.column_stack([c[0] + radius * np.cos(a), c[1] + radius * np.sin(a), z])


def dets(*xy):
    xy = np.asarray(xy, float).reshape(-1, 2)
    return PersonDetections(np.column_stack([xy, np.full(len(xy), 0.9)]), np.tile([0.5, 0.5, 1.7], (len(xy), 1)),
                            np.full(len(xy), 100))


def test_detection_finds_each_person_and_drops_noise():
    rng = np.random.default_rng(0)
    sensor = np.array([0.0, 0.0, 1.0])
    a, b = person_points([3.0, 0.5], [0, 0], rng), person_points([3.0, -1.0], [0, 0], rng)
    # label noise: scattered "human" points on a wall, and a small blob (a chair mislabelled)
    wall = np.column_stack([np.full(40, 5.0), rng.uniform(-3, 3, 40), rng.uniform(0, 2.5, 40)])
    blob = rng.normal([2.0, 2.0, 0.4], 0.03, (6, 3))
    pts = np.vstack([a, b, wall, blob])
    labels = np.full(len(pts), HUMAN)
    labels[-3:] = WALL
    d = detect_people(pts, labels, [HUMAN], sensor)
    assert len(d) == 2
    order = np.argsort(d.centroids[:, 1])
    # the depth offset puts the centroid near the axis, not on the visible surface
    np.testing.assert_allclose(d.centroids[order, :2], [[3.0, -1.0], [3.0, 0.5]], atol=0.08)
    assert np.all(d.counts >= 150)


def test_detection_gates_sizes_and_counts_them():
    rng = np.random.default_rng(1)
    wide = np.column_stack([rng.uniform(0, 3, 400), np.full(400, 1.0), rng.uniform(0, 1.8, 400)])  # a 3 m wall
    flat = np.column_stack([rng.uniform(0, 0.5, 100), rng.uniform(3, 3.5, 100), np.full(100, 0.1)])
    # a wall seen from close by: dense, with one point in twelve mislabelled "human"
    wall = np.column_stack([np.full(6000, 1.5), rng.uniform(3, 3.6, 6000), rng.uniform(0.2, 1.6, 6000)])
    wall_labels = np.where(np.arange(6000) % 12 == 0, HUMAN, WALL)
    dropped = Counter()
    d = detect_people(np.vstack([wide, flat, wall]), np.concatenate([np.full(500, HUMAN), wall_labels]), [HUMAN],
                      dropped=dropped)
    assert len(d) == 0
    assert dropped["too_wide"] == 1 and dropped["too_flat"] == 1 and dropped["impure"] == 1


def test_bad_detections_are_dropped_and_counted_without_a_crash():
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))
    bad = PersonDetections(np.array([[np.nan, 1.0, 0.9], [1.0, 1.0, 0.9], [2.0, 2.0, 0.9]]),
                           np.array([[0.5, 0.5, 1.7], [0.5, 0.5, 1.7], [np.inf, 0.5, 1.7]]),
                           np.array([50, 0, 50]))
    assert tr.step(0, 0.0, 0, bad) == []
    assert tr.dropped["bad_detections"] == 3
    assert not tr.tracks
    # points: NaN coordinates among the person's points are counted, the person is still found
    rng = np.random.default_rng(2)
    pts = person_points([2.0, 0.0], [0, 0], rng)
    pts[:5] = np.nan
    tr.update(1, 1.0, 0, pts, np.full(len(pts), HUMAN), np.zeros(3))
    assert tr.dropped["non_finite_points"] == 5
    assert len(tr.tracks) == 1
    # an empty keyframe is fine too
    tr.update(2, 2.0, 0, np.zeros((0, 3)), np.zeros(0, int))
    assert len(tr.log) == 3


def crossing(association: str, dt: float = 0.5) -> dict[int, list[int]]:
    """Two people walk the diagonals of a 4 m square and meet in the middle; the track ids each
    true person got, keyframe by keyframe."""
    tr = PeopleTracker((HUMAN,), PeopleParams(association=association, confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))
    rng = np.random.default_rng(3)
    ids: dict[int, list[int]] = {0: [], 1: []}
    for k, t in enumerate(np.arange(0.0, 5.65, dt)):
        a = np.array([0.0, 0.0]) + t * np.array([1.0, 1.0]) / np.sqrt(2)
        b = np.array([0.0, 4.0]) + t * np.array([1.0, -1.0]) / np.sqrt(2)
        noisy = np.vstack([a, b]) + rng.normal(0, 0.05, (2, 2))
        owner = tr.step(k, t, 0, dets(*noisy))
        ids[0].append(owner[0])
        ids[1].append(owner[1])
    return ids


def test_two_people_crossing_keep_their_ids():
    ids = crossing("kalman")
    assert len(set(ids[0])) == 1 and len(set(ids[1])) == 1
    assert ids[0][0] != ids[1][0]


def test_nearest_neighbour_association_swaps_the_crossing_ids():
    """The same crossing with nearest-neighbour association swaps the people: the test above
    therefore fails without the motion model."""
    ids = crossing("nearest")
    assert len(set(ids[0])) > 1 or len(set(ids[1])) > 1


def test_birth_after_confirmation_and_death_after_unseen():
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=3, max_unseen=3.0, tentative_unseen=1.5))
    tr.set_submap_pose(0, np.eye(4))
    for k in range(2):
        tr.step(k, float(k), 0, dets([1.0 + 0.5 * k, 0.0]))
    assert tr.confirmed() == []
    tr.step(2, 2.0, 0, dets([2.0, 0.0]))
    assert [t.id for t in tr.confirmed()] == [0]
    tr.step(3, 3.0, 0, dets())  # unseen for a while: still alive
    assert 0 in tr.tracks
    tr.step(4, 5.5, 0, dets())
    assert 0 not in tr.tracks and [t.id for t in tr.ended] == [0]
    # a lone false detection never becomes a person
    tr.step(5, 6.0, 0, dets([9.0, 9.0]))
    tr.step(6, 8.0, 0, dets())
    assert [t.id for t in tr.confirmed()] == [0]


def test_pgo_correction_moves_the_tracks():
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))
    tr.set_submap_pose(1, yaw_pose(5.0, 0.0, 0.0, 0.0))
    for k in range(4):  # a person walking +x, seen from submap 1
        tr.step(k, float(k), 1, dets([6.0 + 0.8 * k, 1.0]))
    (t,) = tr.confirmed()
    before = tr.positions(t)
    velocity = t.x[2:].copy()
    # PGO moves submap 1: a quarter turn about its origin and 0.5 m in y
    moved = yaw_pose(5.0, 0.5, 0.0, np.pi / 2)
    tr.set_submap_pose(1, moved)
    after = tr.positions(t)
    D = moved @ np.linalg.inv(yaw_pose(5.0, 0.0, 0.0, 0.0))
    np.testing.assert_allclose(after, before @ D[:3, :3].T + D[:3, 3], atol=1e-9)
    np.testing.assert_allclose(t.x[2:], D[:2, :2] @ velocity, atol=1e-9)
    # the next detection, in the corrected frame, continues the same track
    nxt = D[:3, :3] @ np.array([6.0 + 0.8 * 4, 1.0, 0.0]) + D[:3, 3]
    assert tr.step(4, 4.0, 1, dets(nxt[:2])) == [t.id]
    # a submap the track is not anchored in leaves it alone
    tr.set_submap_pose(0, yaw_pose(3.0, 3.0, 0.0, 1.0))
    np.testing.assert_allclose(tr.positions(t)[:-1], after, atol=1e-9)


@pytest.mark.parametrize("n", [0, 1])
def test_detection_with_too_few_points(n):
    d = detect_people(np.zeros((n, 3)), np.full(n, HUMAN), [HUMAN])
    assert len(d) == 0


def walk(tracker: PeopleTracker, people, stamps) -> dict[int, list[int]]:
    """Step ``tracker`` through ``stamps``; ``people`` maps a name to a function of time giving the
    person's floor position, or None while they are out of sight. The track ids each person got."""
    ids: dict[int, list[int]] = {k: [] for k in people}
    for k, t in enumerate(stamps):
        seen = [(name, xy) for name, f in people.items() if (xy := f(t)) is not None]
        owner = tracker.step(k, float(t), 0, dets(*[xy for _, xy in seen]))
        for (name, _), o in zip(seen, owner, strict=True):
            ids[name].append(o)
    return ids


def test_a_passer_by_does_not_take_the_id_of_a_person_out_of_sight():
    """A walks east and goes out of sight for 5 s; meanwhile B, walking the other way on the next
    lane, appears 1.4 m from where A was last seen (but 2.5 m from where A would be by now). A
    single detection near where a track was lost is no evidence that it is that person: B must
    get a new id, and A, back in sight on their way, keep their own. (Re-acquiring a lost track by
    its distance from where it was last seen gives B A's id here, and A a new one.)"""
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))
    a = lambda t: None if 3.0 < t < 8.0 else np.array([0.6 * t, 0.0])  # noqa: E731
    b = lambda t: None if t < 5.0 else np.array([0.8 - 1.0 * (t - 5.0), 1.0])  # noqa: E731
    ids = walk(tr, {0: a, 1: b}, np.arange(0.0, 10.01, 0.5))
    assert len(ids[0]) == 12 and len(ids[1]) == 11
    assert len(set(ids[0])) == 1, ids[0]
    assert len(set(ids[1])) == 1, ids[1]
    assert ids[0][0] != ids[1][0]


def test_a_person_who_stood_out_of_sight_is_taken_up_again():
    """A walks east, goes out of sight for 6 s and stands still for 4 of them, so the motion model's
    prediction misses them by 2.4 m when they are back: the young track that agrees with the lost
    one walking on, both ways, continues it (one id)."""
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))

    def a(t):
        if 3.0 < t < 9.0:
            return None
        return np.array([0.6 * t if t <= 4.0 else 2.4 + 0.6 * max(t - 8.0, 0.0), 0.0])

    ids = walk(tr, {0: a}, np.arange(0.0, 12.01, 0.5))
    assert tr.reacquired == 1
    # the keyframe that first saw A again named a new track; the log now names A's
    assert {int(i) for rec in tr.log for i in rec.tracks} == {ids[0][0]}
    (track,) = tr.confirmed()
    assert len(track.stamps) == len(ids[0]) == 14 and list(tr.tracks) == [track.id]


def test_a_person_who_turned_back_out_of_sight_keeps_their_id_and_a_passer_by_does_not_take_it():
    """A walks east to the end of a corridor out of sight, turns back and is seen again walking
    west on the same line; B walks west too, 1 m to the side, and comes into sight first. Carried
    on straight, neither meets A's lost track; walking on to a turning point and back along A's
    line explains A and not B."""
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))

    def a(t):  # east at 0.8 m/s to x = 5 (t = 6.25), then back west
        if 3.0 < t < 9.0:
            return None
        return np.array([0.8 * t if t <= 6.25 else 5.0 - 0.8 * (t - 6.25), 0.0])

    b = lambda t: None if t < 7.0 else np.array([4.0 - 0.8 * (t - 7.0), 1.0])  # noqa: E731
    walk(tr, {0: a, 1: b}, np.arange(0.0, 12.01, 0.5))
    assert tr.reacquired == 1
    names = {}
    for rec in tr.log:
        for (xy, tid) in zip(rec.refs[:, :2], rec.tracks.tolist(), strict=True):
            names.setdefault(int(abs(xy[1]) > 0.5), set()).add(tid)  # 0: A's line, 1: B's
    assert len(names[0]) == 1 and len(names[1]) == 1 and names[0] != names[1]



def test_a_person_who_turned_back_is_judged_against_the_line_they_walked_not_the_last_velocity():
    """A walks east along y = 0; the last two detections before A goes out of sight lie 0.1 m to
    either side (detection noise), so the filter's heading swings by several degrees. A walks on to
    the end, turns back and is seen again 4 m further on than where they were lost, on their line.
    The line of the last velocity passes more than half a metre off there (as for a passer-by in the
    next lane: no); the line fitted to A's last seconds of samples passes through (A, one id)."""
    tr = PeopleTracker((HUMAN,), PeopleParams(confirm_hits=2))
    tr.set_submap_pose(0, np.eye(4))

    def a(t):  # east at 0.8 m/s to x = 10 (t = 12.5), then back west; out of sight for 5 < t < 15
        if 5.0 < t < 15.0:
            return None
        x = 0.8 * t if t <= 12.5 else 10.0 - 0.8 * (t - 12.5)
        return np.array([x, {4.0: -0.1, 5.0: 0.1}.get(float(t), 0.0)])

    walk(tr, {0: a}, np.arange(0.0, 20.01, 1.0))
    assert tr.reacquired == 1
    assert len({int(i) for rec in tr.log for i in rec.tracks}) == 1  # the log names one person
