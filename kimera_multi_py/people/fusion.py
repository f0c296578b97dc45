"""The team's people: every robot's confirmed tracks fused into one set of people
(docs/algorithms/people.md).

Two tracks of different robots follow the same person when they were seen at the same time in the
same place: at the stamps of one track that the other covers (a sample of it within ``max_gap``
seconds on either side, positions interpolated), the median horizontal distance is at most
``link_distance`` over at least ``min_common`` stamps. Pairs are joined in order of that distance,
never joining two tracks of one robot that overlap in time (that robot saw two people). A fused
person's id is the smallest team id of its tracks (``source << 24 | track id``), so robots that hold
the same tables give the same people the same ids.

Across gaps. People look alike, so a person seen again after every robot lost sight of them is a
new group of tracks. Groups are then chained into people as the fewest people that explain them
(a minimum path cover of the groups, by maximum bipartite matching): a group may follow another
that ended before it began, when walking at ``max_speed`` from where the first was last seen
reaches where the second was first seen (plus ``link_distance``). Only the links that every
minimum cover shares are made (an edge every maximum matching holds): one person lost and seen
again is chained, while two people lost and two seen again, each reachable from both, stay four
groups. It assumes nobody enters unseen while somebody known is out of sight and could be them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.cluster.hierarchy import DisjointSet
from scipy.sparse import csr_array
from scipy.sparse.csgraph import breadth_first_order, connected_components, maximum_bipartite_matching

from kimera_multi_py.mapping.object_fusion import TEAM_ID_SHIFT


@dataclass
class TeamTrack:
    source: int
    stamps: np.ndarray  # (n,) increasing
    positions: np.ndarray  # (n, 3)


def _distance(a: TeamTrack, b: TeamTrack, max_gap: float, min_common: int) -> float:
    """Median horizontal distance of ``b`` to ``a`` at the stamps of ``a`` that ``b`` covers (inf: too few)."""
    t = a.stamps[(a.stamps >= b.stamps[0] - max_gap) & (a.stamps <= b.stamps[-1] + max_gap)]
    if len(t) < min_common:
        return np.inf
    i = np.clip(np.searchsorted(b.stamps, t), 1, max(len(b.stamps) - 1, 1))
    near = np.minimum(np.abs(b.stamps[i - 1] - t), np.abs(b.stamps[np.minimum(i, len(b.stamps) - 1)] - t))
    ok = near <= max_gap
    if ok.sum() < min_common:
        return np.inf
    bx = np.interp(t[ok], b.stamps, b.positions[:, 0])
    by = np.interp(t[ok], b.stamps, b.positions[:, 1])
    pa = a.positions[(a.stamps >= b.stamps[0] - max_gap) & (a.stamps <= b.stamps[-1] + max_gap)][ok]
    return float(np.median(np.hypot(pa[:, 0] - bx, pa[:, 1] - by)))


def _overlap(a: TeamTrack, b: TeamTrack) -> bool:
    return bool(a.stamps[0] <= b.stamps[-1] and b.stamps[0] <= a.stamps[-1])


def forced_links(starts: np.ndarray, ends: np.ndarray, first: np.ndarray, last: np.ndarray, max_speed: float,
                 slack: float) -> list[tuple[int, int]]:
    """The links ``(a, b)`` (group ``b`` is group ``a``'s person seen again) that every minimum path
    cover of the groups holds (module docstring). ``starts``/``ends``: each group's first and last
    stamp; ``first``/``last``: its first and last horizontal position.

    A maximum matching's edge is in every maximum matching unless an alternating path or cycle can
    swap it out: in the digraph with unmatched edges from "before" to "after" nodes and matched
    edges back, it lies on a cycle (both ends in one strongly connected component), or its
    "after" end is reached from an unmatched "before" node, or (in the reverse digraph) its
    "before" end from an unmatched "after" node. Linear in the links (Tassa, 2012)."""
    n = len(starts)
    gap = starts[None, :] - ends[:, None]
    reach = np.linalg.norm(first[None, :, :2] - last[:, None, :2], axis=2) <= max_speed * gap + slack
    a, b = np.nonzero((gap > 0) & reach)
    if not len(a):
        return []
    match = maximum_bipartite_matching(csr_array((np.ones(len(a)), (a, b)), shape=(n, n)), perm_type="column")
    matched = match[a] == b
    # nodes 0..n-1 "before" (a group's end), n..2n-1 "after" (a group's start); node 2n: the source
    src = np.where(matched, n + b, a)
    dst = np.where(matched, a, n + b)
    D = csr_array((np.ones(len(a)), (src, dst)), shape=(2 * n + 1, 2 * n + 1))
    _, scc = connected_components(D, directed=True, connection="strong")
    free_before = np.flatnonzero(match < 0)
    free_after = n + np.setdiff1d(np.arange(n), match[match >= 0])
    lo, hi = a[matched], b[matched]
    swappable = scc[lo] == scc[n + hi]
    for free, graph, end in ((free_before, D, n + hi), (free_after, D.T.tocsr(), lo)):
        if len(free):
            G = graph.tolil()
            G[2 * n, free] = 1  # one source before every free node
            seen = breadth_first_order(G.tocsr(), 2 * n, directed=True, return_predecessors=False)
            swappable |= np.isin(end, seen)
    return [(int(x), int(y)) for x, y, s in zip(lo, hi, swappable, strict=True) if not s]


def fuse_people(tracks: Mapping[int, TeamTrack], link_distance: float = 0.6, max_gap: float = 1.5,
                min_common: int = 2, max_speed: float = 2.0) -> list[dict[str, Any]]:
    """Fuse tracks keyed by team id into people: ``id``, ``stamps``, ``positions`` (sorted by stamp),
    ``members`` (team ids of the tracks fused), ``sources``. ``max_speed`` (m/s) bounds how far a
    person walks while nobody sees them (0: no chaining across gaps)."""
    ids = sorted(int(k) for k in tracks if len(tracks[k].stamps))
    pairs = []
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            ta, tb = tracks[a], tracks[b]
            if ta.source == tb.source or not _overlap(ta, tb):
                continue
            d = min(_distance(ta, tb, max_gap, min_common), _distance(tb, ta, max_gap, min_common))
            if d <= link_distance:
                pairs.append((d, a, b))
    groups = DisjointSet(ids)
    for _, a, b in sorted(pairs):
        if groups.connected(a, b):
            continue
        ga, gb = groups.subset(a), groups.subset(b)
        if any(tracks[x].source == tracks[y].source and _overlap(tracks[x], tracks[y]) for x in ga for y in gb):
            continue
        groups.merge(a, b)
    if max_speed > 0:
        _chain(tracks, groups, max_speed, link_distance)
    out = []
    for members in sorted((sorted(s) for s in groups.subsets()), key=lambda m: m[0]):
        stamps = np.concatenate([tracks[m].stamps for m in members])
        pos = np.concatenate([tracks[m].positions for m in members]).reshape(-1, 3)
        order = np.argsort(stamps, kind="stable")
        out.append({"id": members[0], "stamps": stamps[order].tolist(), "positions": pos[order].tolist(),
                    "members": members, "sources": sorted({m >> TEAM_ID_SHIFT for m in members})})
    return out


def _chain(tracks: Mapping[int, TeamTrack], groups: DisjointSet, max_speed: float, slack: float) -> None:
    """Merge the groups that every minimum cover chains (:func:`forced_links`)."""
    subsets = sorted((sorted(s) for s in groups.subsets()), key=lambda m: m[0])
    if len(subsets) < 2:
        return
    ends = []
    for members in subsets:
        st = np.concatenate([tracks[m].stamps for m in members])
        pos = np.concatenate([tracks[m].positions for m in members]).reshape(-1, 3)
        ends.append((st.min(), st.max(), pos[np.argmin(st)], pos[np.argmax(st)]))
    starts, stops, first, last = (np.array([e[k] for e in ends]) for k in range(4))
    for a, b in forced_links(starts, stops, first, last, max_speed, slack):
        groups.merge(subsets[a][0], subsets[b][0])
