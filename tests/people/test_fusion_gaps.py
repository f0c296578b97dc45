"""The team's people across gaps (kimera_multi_py.people.fusion): groups of tracks that only one
person can explain are chained; ambiguous ones stay apart."""

from __future__ import annotations

import numpy as np

from kimera_multi_py.mapping.object_fusion import team_id
from kimera_multi_py.people.fusion import TeamTrack, forced_links, fuse_people


def _walk(robot: int, t0: float, t1: float, start: tuple[float, float], velocity: tuple[float, float]) -> TeamTrack:
    t = np.arange(t0, t1 + 1e-9, 0.5)
    xy = np.asarray(start) + (t - t0)[:, None] * np.asarray(velocity)
    return TeamTrack(robot, t, np.column_stack([xy, np.full(len(t), 0.9)]))


def test_one_person_glimpsed_by_robots_in_turn_is_one_person():
    """A person walking a corridor, seen in three glimpses far apart in time by three robots."""
    tracks = {team_id(1, 0): _walk(1, 10, 14, (0, 0), (0.8, 0)),
              team_id(2, 3): _walk(2, 40, 45, (21, 0), (-0.8, 0)),
              team_id(0, 7): _walk(0, 90, 95, (2, 0), (0.8, 0))}
    (person,) = fuse_people(tracks)
    assert person["members"] == sorted(tracks) and person["id"] == min(tracks)
    assert len(fuse_people(tracks, max_speed=0.0)) == 3  # without chaining: three people


def test_two_people_lost_and_two_seen_again_stay_apart():
    """Either returning glimpse could be either person: no cover forces a link, nothing is chained
    (nearest-first chaining would pair them, and could swap them)."""
    tracks = {team_id(0, 0): _walk(0, 0, 5, (0, 0), (1, 0)),
              team_id(0, 1): _walk(0, 0, 5, (0, 3), (1, 0)),
              team_id(1, 0): _walk(1, 30, 35, (8, 0), (1, 0)),
              team_id(1, 1): _walk(1, 30, 35, (8, 3), (1, 0))}
    assert len(fuse_people(tracks)) == 4


def test_a_glimpse_only_one_person_could_walk_to_is_theirs():
    """B is 60 m away: in 10 s only A reaches the later glimpse C. A glimpse 50 m from where A was
    last seen, 35 s later (1.4 m/s), is A's at a bound of 2 m/s and someone else's at 1 m/s."""
    a, b = team_id(0, 0), team_id(1, 0)
    c, d = team_id(2, 0), team_id(2, 1)
    tracks = {a: _walk(0, 0, 5, (0, 0), (1, 0)), b: _walk(1, 0, 5, (60, 0), (1, 0)),
              c: _walk(2, 15, 20, (12, 0), (1, 0))}
    people = {tuple(p["members"]) for p in fuse_people(tracks)}
    assert people == {(a, c), (b,)}
    far = {a: tracks[a], d: _walk(2, 40, 42, (55, 0), (0, 1))}
    assert len(fuse_people(far, max_speed=2.0)) == 1
    assert len(fuse_people(far, max_speed=1.0)) == 2


def test_groups_that_overlap_in_time_are_never_chained():
    tracks = {team_id(0, 0): _walk(0, 0, 10, (0, 0), (0.5, 0)),
              team_id(1, 0): _walk(1, 8, 20, (20, 0), (0.5, 0))}
    assert len(fuse_people(tracks)) == 2


def test_forced_links_are_the_edges_every_maximum_matching_holds():
    # groups 0 -> 2 and 1 -> 2 both possible, 1 -> 3 only: 0 -> 2 and 1 -> 3 are forced
    starts, ends = np.array([0.0, 0.0, 10.0, 10.0]), np.array([1.0, 1.0, 11.0, 11.0])
    first = np.array([[0, 0], [5, 0], [3, 0], [30, 0]], float)
    last = np.array([[0, 0], [16, 0], [3, 0], [30, 0]], float)
    assert sorted(forced_links(starts, ends, first, last, 2.0, 0.5)) == [(0, 2), (1, 3)]
    # move group 3 out of everyone's reach: 0 -> 2 and 1 -> 2 compete, neither is forced
    first[3] = [200, 0]
    assert forced_links(starts, ends, first, last, 2.0, 0.5) == []


def _forced_by_removal(starts, ends, first, last, max_speed, slack):
    """The definition itself: matched links whose removal shrinks the maximum matching."""
    from scipy.sparse import csr_array
    from scipy.sparse.csgraph import maximum_bipartite_matching

    n = len(starts)
    gap = starts[None, :] - ends[:, None]
    reach = np.linalg.norm(first[None, :, :2] - last[:, None, :2], axis=2) <= max_speed * gap + slack
    links = np.argwhere((gap > 0) & reach)

    def size(ls):
        if not len(ls):
            return 0
        g = csr_array((np.ones(len(ls)), (ls[:, 0], ls[:, 1])), shape=(n, n))
        return int((maximum_bipartite_matching(g, perm_type="column") >= 0).sum())

    full = size(links)
    return sorted((int(x), int(y)) for x, y in links
                  if size(links[~((links[:, 0] == x) & (links[:, 1] == y))]) < full)


def test_forced_links_agree_with_the_definition_on_random_groups():
    rng = np.random.default_rng(7)
    for trial in range(60):
        n = int(rng.integers(2, 25))
        starts = np.sort(rng.uniform(0, 200, n))
        ends = starts + rng.uniform(1, 20, n)
        first, last = rng.uniform(0, 30, (n, 2)), rng.uniform(0, 30, (n, 2))
        speed = float(rng.choice([0.3, 1.0, 2.0]))
        assert sorted(forced_links(starts, ends, first, last, speed, 0.6)) == \
            _forced_by_removal(starts, ends, first, last, speed, 0.6), trial
