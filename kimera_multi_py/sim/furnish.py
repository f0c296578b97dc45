"""Procedural furniture for generated rooms and halls, and a collision-free tour through each.

Used by :mod:`kimera_multi_py.sim.generate` (see docs/simulator.md, generated buildings). A room
kind (office, meeting, lounge, ...) draws furniture groups -- a desk with its monitor and chair,
a row of cabinets, a bed, a meeting table with chairs -- that stand against a wall or as an
island. A group is kept only if it stays inside the room, leaves a gap to every group placed
before it and keeps out of the zone in front of each opening (door leaf and approach).

The tour is chosen afterwards on a 5 cm grid of the room: a cell is free when it is farther than
the robot's radius plus a margin from furniture, door leaves and walls. Each next tour point is
the free cell, visible from the previous point along a straight free segment, farthest from the
points chosen so far; the first and the last point see the approach point of every opening, so
a route planned through any door (:meth:`World.plan_route`) never meets an obstacle.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from kimera_multi_py.sim.scenario import LayoutConfig, ObjectConfig
from kimera_multi_py.sim.world import DOOR_APPROACH, ROBOT_RADIUS

RES = 0.05  # grid cell (m)
HALF_WALL = 0.05  # half the generated buildings' wall thickness
GAP = 0.12  # between furniture groups, and between furniture and walls
CLEAR = ROBOT_RADIUS + 0.15  # a tour's distance to obstacles (check_path needs the radius)
POINT_CLEAR = 0.6  # a tour point's least distance to walls and furniture (m)
MAX_CANDIDATES = 400  # tour point candidates drawn from the free cells
ROOM_KINDS = ("office", "meeting", "lounge", "bedroom", "storage", "kitchen", "lab")
# wall frames: origin corner (as fractions of the room's w, d) and angle; +u along, +v inwards
_WALLS = {"S": ((0, 0), 0.0), "E": ((1, 0), 90.0), "N": ((1, 1), 180.0), "W": ((0, 1), -90.0)}
_NORMALS = {"S": (0.0, 1.0), "N": (0.0, -1.0), "W": (1.0, 0.0), "E": (-1.0, 0.0)}


@dataclass(frozen=True)
class Opening:
    """A door of the space: its wall, centre along that wall (local x for S/N, local y for W/E)."""

    wall: str
    at: float
    width: float = 1.0
    leaf: bool = True

    def point(self, w: float, d: float, depth: float = 0.0) -> np.ndarray:
        base = {"S": (self.at, 0.0), "N": (self.at, d), "W": (0.0, self.at), "E": (w, self.at)}[self.wall]
        return np.array(base) + depth * np.array(_NORMALS[self.wall])


@dataclass
class Item:
    """One object in a group's frame: ``u`` along, ``v`` away from the anchor."""

    cls: str
    u: float
    v: float
    size: tuple[float, float, float]
    yaw: float = 0.0
    shape: str = "box"
    elevation: float = 0.0


def _r(x: float, step: float = 0.05) -> float:
    return round(round(float(x) / step) * step, 2)


def _pick(rng: np.random.Generator, *values: float) -> float:
    return float(values[int(rng.integers(len(values)))])


# ---- furniture groups (wall groups: v = 0 at the wall face; islands: centred on the anchor) ----
def desk(rng: np.random.Generator) -> list[Item]:
    tw, td = _pick(rng, 1.2, 1.4, 1.6), _pick(rng, 0.6, 0.7, 0.8)
    return [Item("table", 0.0, td / 2, (tw, td, 0.75)),
            Item("monitor", _r(rng.uniform(-0.25, 0.25) * tw), 0.15, (_pick(rng, 0.5, 0.6), 0.12, 0.4),
                 elevation=0.75),
            Item("chair", _r(rng.uniform(-0.2, 0.2)), td + 0.35, (0.5, 0.5, _pick(rng, 0.85, 0.9, 1.0)),
                 yaw=_r(rng.uniform(-25, 25), 1.0))]


def cabinets(rng: np.random.Generator, low: int = 1, high: int = 3, height: float | None = None) -> list[Item]:
    n = int(rng.integers(low, high + 1))
    w, dd = _pick(rng, 0.6, 0.8, 1.0, 1.2), _pick(rng, 0.4, 0.5, 0.6)
    h = height if height is not None else _pick(rng, 1.2, 1.5, 1.8, 2.0)
    step = w + 0.15
    return [Item("cabinet", (k - (n - 1) / 2) * step, dd / 2, (w, dd, h)) for k in range(n)]


def sofa(rng: np.random.Generator) -> list[Item]:
    return [Item("sofa", 0.0, 0.45, (_pick(rng, 1.6, 1.8, 2.0, 2.2), 0.9, 0.8))]


def bed(rng: np.random.Generator) -> list[Item]:
    bw = _pick(rng, 1.4, 1.6, 1.8)
    items = [Item("bed", 0.0, 1.0, (bw, 2.0, 0.5))]
    if rng.random() < 0.7:
        items.append(Item("cabinet", bw / 2 + 0.4, 0.25, (0.45, 0.4, 0.55)))
    return items


def plant(rng: np.random.Generator) -> list[Item]:
    s = _pick(rng, 0.4, 0.5, 0.6)
    return [Item("plant", 0.0, s / 2 + 0.05, (s, s, _pick(rng, 0.9, 1.1, 1.3, 1.5)), shape="ellipsoid")]


def sideboard(rng: np.random.Generator) -> list[Item]:
    tw = _pick(rng, 1.0, 1.2, 1.4)
    items = [Item("table", 0.0, 0.25, (tw, 0.45, 0.8))]
    if rng.random() < 0.5:  # a screen on it
        items.append(Item("monitor", 0.0, 0.2, (_pick(rng, 0.8, 1.0), 0.1, 0.55), elevation=0.8))
    return items


def screen(rng: np.random.Generator) -> list[Item]:
    return [Item("monitor", 0.0, 0.06, (_pick(rng, 1.0, 1.2, 1.4), 0.08, 0.7), elevation=1.0)]


def meeting_table(rng: np.random.Generator) -> list[Item]:
    tw, td = _pick(rng, 2.0, 2.4, 2.8), _pick(rng, 1.0, 1.2)
    per_side = int(rng.integers(2, 4))
    items = [Item("table", 0.0, 0.0, (tw, td, 0.75))]
    for side in (-1.0, 1.0):
        for k in range(per_side):
            items.append(Item("chair", (k - (per_side - 1) / 2) * tw / per_side, side * (td / 2 + 0.35),
                              (0.5, 0.5, 0.9), yaw=_r(rng.uniform(-15, 15), 1.0)))
    return items


def coffee(rng: np.random.Generator) -> list[Item]:
    return [Item("table", 0.0, 0.0, (_pick(rng, 0.8, 1.0, 1.2), _pick(rng, 0.5, 0.6), 0.45))]


def dining(rng: np.random.Generator) -> list[Item]:
    tw, td = _pick(rng, 1.2, 1.4), 0.8
    items = [Item("table", 0.0, 0.0, (tw, td, 0.75))]
    for side in (-1.0, 1.0) if rng.random() < 0.6 else (1.0,):
        items.append(Item("chair", _r(rng.uniform(-0.3, 0.3)), side * (td / 2 + 0.35), (0.5, 0.5, 0.9),
                          yaw=_r(rng.uniform(-20, 20), 1.0)))
    return items


def workbench(rng: np.random.Generator) -> list[Item]:
    return [Item("table", 0.0, 0.0, (1.6, 0.8, 0.9)),
            Item("monitor", -0.4, 0.0, (0.5, 0.12, 0.4), elevation=0.9),
            Item("monitor", 0.4, 0.0, (0.5, 0.12, 0.4), yaw=180.0, elevation=0.9)]


Group = Callable[[np.random.Generator], list[Item]]
# kind -> [(group, placement, least, most)]; placement "wall" or "island"
RECIPES: dict[str, list[tuple[Group, str, int, int]]] = {
    "office": [(desk, "wall", 1, 3), (cabinets, "wall", 0, 1), (plant, "wall", 0, 1), (sofa, "wall", 0, 1)],
    "meeting": [(meeting_table, "island", 1, 1), (screen, "wall", 1, 1), (plant, "wall", 1, 2),
                (cabinets, "wall", 0, 1)],
    "lounge": [(sofa, "wall", 1, 3), (coffee, "island", 1, 2), (plant, "wall", 1, 2), (sideboard, "wall", 0, 1)],
    "bedroom": [(bed, "wall", 1, 1), (cabinets, "wall", 1, 1), (desk, "wall", 0, 1), (plant, "wall", 0, 1)],
    "storage": [(cabinets, "wall", 2, 4), (coffee, "island", 0, 1), (plant, "wall", 0, 1)],
    "kitchen": [(lambda g: cabinets(g, 2, 3, 0.9), "wall", 1, 2), (dining, "island", 1, 1),
                (plant, "wall", 0, 1), (sideboard, "wall", 0, 1)],
    "lab": [(desk, "wall", 2, 3), (workbench, "island", 0, 1), (cabinets, "wall", 1, 1)],
    "hall": [(dining, "island", 1, 3), (coffee, "island", 1, 2), (meeting_table, "island", 0, 1),
             (sofa, "wall", 1, 3), (plant, "wall", 2, 4), (cabinets, "wall", 0, 2), (sideboard, "wall", 0, 1)],
}


class _Plan:
    """A room's grid: cell centres, furniture footprints, and the zones kept clear of furniture."""

    def __init__(self, w: float, d: float, openings: list[Opening], strip: float) -> None:
        self.w, self.d, self.openings = w, d, openings
        self.xs = (np.arange(int(np.ceil(w / RES))) + 0.5) * RES
        self.ys = (np.arange(int(np.ceil(d / RES))) + 0.5) * RES
        shape = (len(self.xs), len(self.ys))
        self.occupied = np.zeros(shape, dtype=bool)  # furniture footprints
        self.blocked = np.zeros(shape, dtype=bool)  # door leaves (obstacles, not furniture)
        self.keepout = np.zeros(shape, dtype=bool)
        for o in openings:
            n = np.array(_NORMALS[o.wall])
            along = np.abs(n[::-1])
            reach = o.width / 2 + (1.3 if o.leaf else 0.5)
            depth = max(1.3, strip)
            self._box(self.keepout, o.point(w, d, depth / 2), along * reach + np.abs(n) * depth / 2)
            if o.leaf:  # the leaf stands on one side of the opening; keep both clear
                for sign in (-1.0, 1.0):
                    c = o.point(w, d, 0.1) + sign * along * (o.width / 2 + 0.5)
                    self._box(self.blocked, c, along * 0.5 + np.abs(n) * 0.1)
            if strip > 0:  # halls: a free lane along the wall, for routes passing between openings
                lane = o.point(w, d, strip / 2) * np.abs(n) + np.array([w, d]) / 2 * along
                self._box(self.keepout, lane, along * np.array([w, d]) / 2 + np.abs(n) * strip / 2)

    def _box(self, mask: np.ndarray, center: np.ndarray, half: np.ndarray) -> None:
        ix = (np.abs(self.xs - center[0]) <= half[0])
        iy = (np.abs(self.ys - center[1]) <= half[1])
        mask[np.ix_(ix, iy)] = True

    def footprint(self, it: tuple[float, float, float, float, float, str], grow: float) -> tuple[
            tuple[slice, slice], np.ndarray] | None:
        """Cells of an object's footprint grown by ``grow``; None if it leaves the room."""
        x, y, sx, sy, yaw, shape = it
        c, s = np.cos(np.deg2rad(yaw)), np.sin(np.deg2rad(yaw))
        ex, ey = abs(c) * sx / 2 + abs(s) * sy / 2, abs(s) * sx / 2 + abs(c) * sy / 2
        lim = HALF_WALL + 0.03
        if x - ex < lim or y - ey < lim or x + ex > self.w - lim or y + ey > self.d - lim:
            return None
        i0, i1 = np.searchsorted(self.xs, [x - ex - grow, x + ex + grow])
        j0, j1 = np.searchsorted(self.ys, [y - ey - grow, y + ey + grow])
        dx, dy = np.meshgrid(self.xs[i0:i1] - x, self.ys[j0:j1] - y, indexing="ij")
        lu, lv = c * dx + s * dy, -s * dx + c * dy
        hu, hv = sx / 2 + grow, sy / 2 + grow
        if shape == "ellipsoid":
            inside = (lu / hu) ** 2 + (lv / hv) ** 2 <= 1.0
        else:
            inside = (np.abs(lu) <= hu) & (np.abs(lv) <= hv)
        return (slice(i0, i1), slice(j0, j1)), inside

    def place(self, items: list[tuple[float, float, float, float, float, str]]) -> bool:
        """Stamp a group's footprints if every one fits, clear of furniture and keep-out zones."""
        stamps = []
        for it in items:
            grown = self.footprint(it, GAP)
            tight = self.footprint(it, 0.0)
            if grown is None or tight is None:
                return False
            sl, mask = grown
            if np.any(self.occupied[sl] & mask) or np.any(self.keepout[sl] & mask):
                return False
            stamps.append(tight)
        for sl, mask in stamps:
            self.occupied[sl] |= mask
        return True


def _transform(items: list[Item], origin: np.ndarray, angle: float, lift: float) -> list[ObjectConfig]:
    c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
    out = []
    for it in items:
        u, v = it.u, it.v + lift
        x, y = origin[0] + c * u - s * v, origin[1] + s * u + c * v
        yaw = (angle + it.yaw + 180.0) % 360.0 - 180.0
        out.append(ObjectConfig.model_validate({
            "class": it.cls, "shape": it.shape, "xy": (_r(x, 0.01), _r(y, 0.01)),
            "size": tuple(_r(v_) for v_ in it.size), "yaw_deg": round(yaw, 1), "elevation": _r(it.elevation)}))
    return out


def _footprint_args(ob: ObjectConfig) -> tuple[float, float, float, float, float, str]:
    return (ob.xy[0], ob.xy[1], ob.size[0], ob.size[1], ob.yaw_deg, ob.shape)


def _furniture(rng: np.random.Generator, kind: str, plan: _Plan, tries: int = 40) -> list[ObjectConfig]:
    objects: list[ObjectConfig] = []
    w, d = plan.w, plan.d
    for group, where, least, most in RECIPES[kind]:
        scale = max(1, int(round(w * d / 90.0))) if kind == "hall" else 1
        for _ in range(int(rng.integers(least, most + 1)) * scale):
            items = group(rng)
            for _ in range(tries):
                if where == "wall":
                    wall = str(rng.choice(list(_WALLS), p=np.array([w, d, w, d]) / (2 * (w + d))))
                    corner, angle = _WALLS[wall]
                    length = w if wall in "SN" else d
                    origin = np.array([corner[0] * w, corner[1] * d])
                    c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
                    a = rng.uniform(0.3, length - 0.3)
                    obs = _transform(items, origin + a * np.array([c, s]), angle, HALF_WALL + 0.04)
                else:
                    center = np.array([rng.uniform(1.0, max(1.0, w - 1.0)), rng.uniform(1.0, max(1.0, d - 1.0))])
                    angle = _pick(rng, 0.0, 90.0) + _r(rng.uniform(-10, 10), 1.0)
                    obs = _transform(items, center, angle, 0.0)
                if plan.place([_footprint_args(ob) for ob in obs]):
                    objects += obs
                    break
    return objects


def _visible(free: np.ndarray, p: np.ndarray, q: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Which segments ``p -> q[k]`` stay in free cells (sampled every cell)."""
    out = np.zeros(len(q), dtype=bool)
    hi = np.array(free.shape) - 1
    for s in range(0, len(q), chunk):
        qs = q[s:s + chunk]
        n = int(np.ceil(np.max(np.linalg.norm(qs - p, axis=1), initial=0.0) / RES)) + 2
        t = np.linspace(0.0, 1.0, n)
        pts = p[None, None, :] + t[None, :, None] * (qs - p)[:, None, :]
        ij = np.clip(np.floor(pts / RES).astype(np.int64), 0, hi)
        out[s:s + chunk] = np.all(free[ij[..., 0], ij[..., 1]], axis=1)
    return out


def _tour(rng: np.random.Generator, plan: _Plan, points: int) -> list[tuple[float, float]]:
    w, d = plan.w, plan.d
    obstacle = plan.occupied | plan.blocked
    dist = distance_transform_edt(~obstacle) * RES if obstacle.any() else np.full(obstacle.shape, np.inf)
    gx, gy = np.meshgrid(plan.xs, plan.ys, indexing="ij")
    wall = np.minimum(np.minimum(gx, w - gx), np.minimum(gy, d - gy)) - HALF_WALL
    free = (dist > CLEAR + RES) & (wall > CLEAR + RES)
    step = 2 if w * d < 80 else 4  # candidates on a 10 cm (rooms) or 20 cm (halls) lattice
    clearance = np.minimum(dist, wall)
    cand = np.argwhere(free[::step, ::step] & (clearance[::step, ::step] >= POINT_CLEAR)) * step
    if len(cand) == 0:
        return []
    if len(cand) > MAX_CANDIDATES:
        cand = cand[np.sort(rng.permutation(len(cand))[:MAX_CANDIDATES])]
    q = np.column_stack([plan.xs[cand[:, 0]], plan.ys[cand[:, 1]]])
    clearance = clearance[cand[:, 0], cand[:, 1]]
    ports = [o.point(w, d, DOOR_APPROACH) for o in plan.openings]
    sees_ports = np.ones(len(q), dtype=bool)
    for p in ports:
        sees_ports &= _visible(free, p, q)
    chosen: list[int] = []
    for k in range(points):
        ok = sees_ports.copy() if k == 0 else _visible(free, q[chosen[-1]], q)
        if k == points - 1 and np.any(ok & sees_ports):
            ok &= sees_ports
        if not ok.any():
            break
        anchors = np.array(ports + [q[c] for c in chosen])
        spread = np.min(np.linalg.norm(q[:, None, :] - anchors[None], axis=2), axis=1)
        score = spread + np.minimum(clearance, 1.2) + rng.uniform(0.0, 0.4, len(q))
        best = int(np.argmax(np.where(ok, score, -np.inf)))
        if spread[best] < 0.6:
            break
        chosen.append(best)
    ends = [k for k, c in enumerate(chosen) if sees_ports[c]]
    chosen = chosen[: ends[-1] + 1] if ends else []
    return [(_r(q[c, 0], 0.01), _r(q[c, 1], 0.01)) for c in chosen]


def furnish(rng: np.random.Generator, kind: str, size: tuple[float, float], openings: list[Opening],
            tour_points: int = 4) -> LayoutConfig:
    """Furniture of ``kind`` for a ``size`` (w, d) space with these openings, and a tour through it.

    Halls keep a 1.4 m lane along each wall with an opening free of furniture, so routes passing
    from one opening to another cross them in a straight line. A room whose tour comes out shorter
    than three points is furnished again, with fewer islands.
    """
    w, d = size
    strip = 1.4 if kind == "hall" else 0.0
    best: tuple[int, LayoutConfig] | None = None
    for attempt in range(6):
        plan = _Plan(w, d, openings, strip)
        objects = _furniture(rng, kind, plan) if attempt < 5 else []
        tour = _tour(rng, plan, tour_points)
        layout = LayoutConfig(objects=objects, tour=tour)
        score = min(len(tour), 3) * 100 + len(objects)
        if best is None or score > best[0]:
            best = (score, layout)
        if len(tour) >= min(3, tour_points) and len(objects) >= 3:
            break
    assert best is not None
    return best[1]


def signature(layout: LayoutConfig) -> tuple[tuple[str, int], ...]:
    """A layout's object set: how many objects of each class."""
    names = sorted(ob.cls for ob in layout.objects)
    return tuple((n, names.count(n)) for n in sorted(set(names)))
