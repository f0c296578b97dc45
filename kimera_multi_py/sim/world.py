"""The simulated world: an indoor floor plan built from primitives, ray casting and ground truth.

Walls, floors, ceilings, door leaves and furniture are oriented boxes or ellipsoids held in
flat numpy arrays. :meth:`World.raycast` intersects every ray with every primitive at once
(slab test for boxes, quadratic for ellipsoids), chunked over rays to bound memory.
:meth:`World.gt_voxel_grid` rasterises the static world into labels: -1 unknown (outside the
building), 0 free (inside a space), or the class id of the surface / object occupying the cell.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.geometry import so3_exp
from kimera_multi_py.core.semantics import CLASS_IDS, CLASS_NAMES
from kimera_multi_py.sim.scenario import ScenarioConfig

BOX, ELLIPSOID = 0, 1
ROBOT_RADIUS = 0.2
ROBOT_BODY_Z = (0.05, 1.2)  # above the floor, for collision checks
DOOR_APPROACH = 0.7  # m either side of a door a route passes through
_RAY_CHUNK = 2048


@dataclass
class Primitives:
    """A flat set of oriented boxes (half extents) and ellipsoids (radii)."""

    shape: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int8))
    center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    half: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    rot: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    label: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int16))
    names: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.names)

    @staticmethod
    def build(items: list[tuple[int, np.ndarray, np.ndarray, float, int, str]]) -> Primitives:
        """From ``(shape, center, half, yaw, label, name)`` tuples."""
        if not items:
            return Primitives()
        shape, center, half, yaw, label, names = zip(*items, strict=True)
        return Primitives(
            shape=np.array(shape, dtype=np.int8),
            center=np.array(center, dtype=float).reshape(-1, 3),
            half=np.array(half, dtype=float).reshape(-1, 3),
            rot=so3_exp(np.column_stack([np.zeros((len(yaw), 2)), np.array(yaw, dtype=float)])),
            label=np.array(label, dtype=np.int16),
            names=list(names),
        )

    def concat(self, other: Primitives) -> Primitives:
        return Primitives(
            np.concatenate([self.shape, other.shape]),
            np.concatenate([self.center, other.center]),
            np.concatenate([self.half, other.half]),
            np.concatenate([self.rot, other.rot]),
            np.concatenate([self.label, other.label]),
            self.names + other.names,
        )

    def subset(self, mask: np.ndarray) -> Primitives:
        idx = np.flatnonzero(mask)
        return Primitives(
            self.shape[idx], self.center[idx], self.half[idx], self.rot[idx], self.label[idx],
            [self.names[i] for i in idx],
        )

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds ``(lo, hi)`` of each primitive, ``(m, 3)`` each."""
        ext = np.einsum("mij,mj->mi", np.abs(self.rot), self.half)
        return self.center - ext, self.center + ext


@dataclass(frozen=True)
class GroundTruthObject:
    """A true object: class, centroid, full box extents and heading."""

    id: int
    cls: str
    centroid: np.ndarray
    size: np.ndarray
    yaw: float
    shape: str
    space: str

    @property
    def label(self) -> int:
        return CLASS_IDS[self.cls]

    def to_dict(self) -> dict[str, object]:
        return {
            "id": self.id, "class": self.cls, "centroid": self.centroid.round(6).tolist(),
            "size": self.size.round(6).tolist(), "yaw": round(self.yaw, 6), "shape": self.shape,
            "space": self.space,
        }


@dataclass
class VoxelGrid:
    """A dense label grid: cell ``(i, j, k)`` spans ``origin + res*[i, i+1) x ...``."""

    origin: np.ndarray
    resolution: float
    labels: np.ndarray  # int8 (nx, ny, nz): -1 unknown, 0 free, >0 class id

    def centers(self) -> np.ndarray:
        """Centres of all cells, ``(nx, ny, nz, 3)``."""
        axes = [self.origin[a] + (np.arange(n) + 0.5) * self.resolution
                for a, n in enumerate(self.labels.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1)

    def index(self, points: np.ndarray) -> np.ndarray:
        """Integer cell indices ``(n, 3)`` of points (may fall outside the grid)."""
        return np.floor((np.asarray(points) - self.origin) / self.resolution).astype(np.int64)

    def label_at(self, points: np.ndarray) -> np.ndarray:
        """Labels at points; -1 for points outside the grid."""
        ijk = self.index(np.atleast_2d(points))
        inside = np.all((ijk >= 0) & (ijk < np.array(self.labels.shape)), axis=1)
        out = np.full(len(ijk), -1, dtype=np.int16)
        i = ijk[inside]
        out[inside] = self.labels[i[:, 0], i[:, 1], i[:, 2]]
        return out


@dataclass(frozen=True)
class Door:
    center: np.ndarray  # (2,)
    normal: np.ndarray  # (2,) unit, pointing from spaces[0] to spaces[1]
    width: float
    spaces: tuple[int, int]


def _yaw_of(normal: np.ndarray) -> float:
    return float(np.arctan2(normal[1], normal[0]))


class World:
    """The static floor plan plus walking humans, built from a :class:`ScenarioConfig`."""

    def __init__(self, cfg: ScenarioConfig) -> None:
        self.cfg = cfg
        b = cfg.building
        self.floor_z = b.floor_z
        self.ceiling_z = b.floor_z + b.height
        self.space_names = [s.name for s in cfg.spaces]
        self.rects = np.array([[*s.min, *s.max] for s in cfg.spaces], dtype=float)
        self.doors = self._find_doors()
        structure = self._structure()
        leaves, leaf_objects = self._door_leaves()
        furniture, objects = self._furniture(start_id=len(leaf_objects))
        self.static = structure.concat(leaves).concat(furniture)
        self.objects: list[GroundTruthObject] = leaf_objects + objects
        self.adjacency = self._adjacency()

    # ---- floor plan ---------------------------------------------------------------------------
    def _find_doors(self) -> list[Door]:
        doors = []
        tol = 1e-6
        for i, d in enumerate(self.cfg.doors):
            p = np.array(d.at, dtype=float)
            touching = []
            for s, (x0, y0, x1, y1) in enumerate(self.rects):
                on_h = (abs(p[1] - y0) < tol or abs(p[1] - y1) < tol) and x0 < p[0] < x1
                on_v = (abs(p[0] - x0) < tol or abs(p[0] - x1) < tol) and y0 < p[1] < y1
                if on_h or on_v:
                    touching.append((s, "h" if on_h else "v"))
            if len(touching) != 2 or touching[0][1] != touching[1][1]:
                raise ConfigError(f"doors[{i}].at", f"{d.at} must lie on a wall shared by exactly two spaces")
            (sa, axis), (sb, _) = touching
            normal = np.array([0.0, 1.0]) if axis == "h" else np.array([1.0, 0.0])
            ca = self.rects[sa].reshape(2, 2).mean(0)
            if np.dot(p - ca, normal) < 0:
                normal = -normal
            doors.append(Door(p, normal, d.width, (sa, sb)))
        return doors

    def _wall_intervals(self) -> list[tuple[str, float, float, float, bool, bool]]:
        """Wall pieces ``(axis, line, a, b, extend_a, extend_b)`` after merging and door cuts."""
        lines: dict[tuple[str, float], list[tuple[float, float]]] = {}
        for x0, y0, x1, y1 in self.rects:
            for axis, line, a, b in (("h", y0, x0, x1), ("h", y1, x0, x1), ("v", x0, y0, y1), ("v", x1, y0, y1)):
                lines.setdefault((axis, round(line, 6)), []).append((a, b))
        pieces = []
        for (axis, line), ivs in sorted(lines.items()):
            merged: list[list[float]] = []
            for a, b in sorted(ivs):
                if merged and a <= merged[-1][1] + 1e-9:
                    merged[-1][1] = max(merged[-1][1], b)
                else:
                    merged.append([a, b])
            cuts = sorted(
                (d.center[0 if axis == "h" else 1] - d.width / 2, d.center[0 if axis == "h" else 1] + d.width / 2)
                for d in self.doors
                if abs(d.center[1 if axis == "h" else 0] - line) < 1e-6
            )
            for a, b in merged:
                segs = [(a, b, True, True)]
                for ca, cb in cuts:
                    nxt = []
                    for sa, sb, ea, eb in segs:
                        if cb <= sa or ca >= sb:
                            nxt.append((sa, sb, ea, eb))
                            continue
                        if ca > sa:
                            nxt.append((sa, ca, ea, False))
                        if cb < sb:
                            nxt.append((cb, sb, False, eb))
                    segs = nxt
                pieces += [(axis, line, sa, sb, ea, eb) for sa, sb, ea, eb in segs if sb - sa > 1e-6]
        return pieces

    def _structure(self) -> Primitives:
        b = self.cfg.building
        t, zc, hz = b.wall_thickness, self.floor_z + b.height / 2, b.height / 2
        items: list[tuple[int, np.ndarray, np.ndarray, float, int, str]] = []
        wall = CLASS_IDS["wall"]
        for n, (axis, line, a, bb, ea, eb) in enumerate(self._wall_intervals()):
            lo = a - (t / 2 if ea else 0.0)
            hi = bb + (t / 2 if eb else 0.0)
            mid, half = (lo + hi) / 2, (hi - lo) / 2
            if axis == "h":
                items.append((BOX, np.array([mid, line, zc]), np.array([half, t / 2, hz]), 0.0, wall, f"wall{n}"))
            else:
                items.append((BOX, np.array([line, mid, zc]), np.array([t / 2, half, hz]), 0.0, wall, f"wall{n}"))
        s = b.slab_thickness
        for (x0, y0, x1, y1), name in zip(self.rects, self.space_names, strict=True):
            c = np.array([(x0 + x1) / 2, (y0 + y1) / 2, 0.0])
            h = np.array([(x1 - x0) / 2 + t / 2, (y1 - y0) / 2 + t / 2, s / 2])
            items.append((BOX, c + [0, 0, self.floor_z - s / 2], h, 0.0, CLASS_IDS["floor"], f"{name}/floor"))
            items.append((BOX, c + [0, 0, self.ceiling_z + s / 2], h, 0.0, CLASS_IDS["ceiling"], f"{name}/ceiling"))
        return Primitives.build(items)

    def _door_leaves(self) -> tuple[Primitives, list[GroundTruthObject]]:
        items: list[tuple[int, np.ndarray, np.ndarray, float, int, str]] = []
        objects: list[GroundTruthObject] = []
        t = self.cfg.building.wall_thickness
        leaf_t, leaf_h = 0.04, min(2.0, self.cfg.building.height - 0.05)
        for i, (d, dc) in enumerate(zip(self.doors, self.cfg.doors, strict=True)):
            if not dc.leaf:
                continue
            sa, sb = d.spaces
            kinds = [self.cfg.spaces[s].kind for s in (sa, sb)]
            side = sb if kinds[1] == "room" and kinds[0] != "room" else sa
            into = d.normal if side == sb else -d.normal
            along = np.array([-d.normal[1], d.normal[0]])
            length = min(d.width, 0.9)
            x0, y0, x1, y1 = self.rects[side]
            offset = t / 2 + 0.03 + leaf_t / 2
            for sign in (1.0, -1.0):  # hinge on whichever side of the opening fits in the room
                c2 = d.center + sign * along * (d.width / 2 + 0.05 + length / 2) + into * offset
                ends = [c2 - along * length / 2, c2 + along * length / 2]
                if all(x0 <= e[0] <= x1 and y0 <= e[1] <= y1 for e in ends):
                    break
            half = np.array([length / 2, leaf_t / 2, leaf_h / 2])
            yaw = _yaw_of(along)
            center = np.array([c2[0], c2[1], self.floor_z + leaf_h / 2])
            items.append((BOX, center, half, yaw, CLASS_IDS["door"], f"door{i}"))
            objects.append(GroundTruthObject(len(objects), "door", center, 2 * half, yaw, "box",
                                             self.space_names[side]))
        return Primitives.build(items), objects

    def _furniture(self, start_id: int) -> tuple[Primitives, list[GroundTruthObject]]:
        items: list[tuple[int, np.ndarray, np.ndarray, float, int, str]] = []
        objects: list[GroundTruthObject] = []
        for space in self.cfg.spaces:
            if space.layout is None:
                continue
            for j, ob in enumerate(self.cfg.layouts[space.layout].objects):
                size = np.array(ob.size, dtype=float)
                center = np.array([space.min[0] + ob.xy[0], space.min[1] + ob.xy[1],
                                   self.floor_z + ob.elevation + size[2] / 2])
                yaw = float(np.deg2rad(ob.yaw_deg))
                shape = BOX if ob.shape == "box" else ELLIPSOID
                items.append((shape, center, size / 2, yaw, CLASS_IDS[ob.cls], f"{space.name}/{ob.cls}{j}"))
                objects.append(GroundTruthObject(start_id + len(objects), ob.cls, center, size, yaw,
                                                 ob.shape, space.name))
        return Primitives.build(items), objects

    def _adjacency(self) -> dict[int, list[tuple[int, int]]]:
        adj: dict[int, list[tuple[int, int]]] = {i: [] for i in range(len(self.rects))}
        for k, d in enumerate(self.doors):
            a, b = d.spaces
            adj[a].append((b, k))
            adj[b].append((a, k))
        return adj

    # ---- routes -------------------------------------------------------------------------------
    def _tour(self, s: int) -> list[np.ndarray]:
        space = self.cfg.spaces[s]
        base = np.array(space.min, dtype=float)
        if space.layout is not None and self.cfg.layouts[space.layout].tour:
            return [base + np.array(p) for p in self.cfg.layouts[space.layout].tour]
        if space.via is not None:
            return [np.array(space.via, dtype=float)]
        return [self.rects[s].reshape(2, 2).mean(0)]

    def _space_path(self, a: int, b: int) -> list[tuple[int, int]]:
        """Shortest door path from space a to b as ``[(space, door), ...]`` (BFS)."""
        prev: dict[int, tuple[int, int] | None] = {a: None}
        queue = deque([a])
        while queue:
            s = queue.popleft()
            if s == b:
                break
            for nb, door in self.adjacency[s]:
                if nb not in prev:
                    prev[nb] = (s, door)
                    queue.append(nb)
        if b not in prev:
            return []
        steps = []
        node = b
        while prev[node] is not None:
            parent, door = prev[node]  # type: ignore[misc]
            steps.append((node, door))
            node = parent
        return steps[::-1]

    def plan_route(self, route: list[str], field_name: str) -> np.ndarray:
        """2-D waypoints visiting ``route`` (space names) in order, through doors."""
        idx = [self.space_names.index(n) for n in route]
        points = self._tour(idx[0])
        cur = idx[0]
        for nxt in idx[1:]:
            steps = self._space_path(cur, nxt)
            if not steps and nxt != cur:
                raise ConfigError(field_name, f"no door path from {self.space_names[cur]!r} "
                                              f"to {self.space_names[nxt]!r}")
            for space, door_i in steps:
                d = self.doors[door_i]
                n = d.normal if d.spaces[1] == space else -d.normal
                points += [d.center - n * DOOR_APPROACH, d.center + n * DOOR_APPROACH]
                if space == nxt:
                    points += self._tour(space)
            cur = nxt
        pts = np.array(points, dtype=float)
        keep = np.ones(len(pts), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-6
        return pts[keep]

    def check_path(self, waypoints: np.ndarray, field_name: str, step: float = 0.05) -> None:
        """Raise ConfigError if a robot's footprint along the path meets a wall or object."""
        lo_z, hi_z = self.floor_z + ROBOT_BODY_Z[0], self.floor_z + ROBOT_BODY_Z[1]
        prim_lo, prim_hi = self.static.aabb()
        solid = (prim_hi[:, 2] > lo_z) & (prim_lo[:, 2] < hi_z)
        P = self.static.subset(solid)
        for k in range(len(waypoints) - 1):
            a, b = waypoints[k], waypoints[k + 1]
            n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
            s = np.linspace(0.0, 1.0, n)[:, None]
            pts = a + s * (b - a)
            inside_building = np.any(
                (pts[:, None, 0] >= self.rects[None, :, 0]) & (pts[:, None, 0] <= self.rects[None, :, 2])
                & (pts[:, None, 1] >= self.rects[None, :, 1]) & (pts[:, None, 1] <= self.rects[None, :, 3]),
                axis=1,
            )
            if not inside_building.all():
                bad = pts[~inside_building][0]
                raise ConfigError(field_name, f"segment {k} ({a[0]:.2f}, {a[1]:.2f}) -> ({b[0]:.2f}, {b[1]:.2f}) "
                                              f"leaves the building at ({bad[0]:.2f}, {bad[1]:.2f})")
            rel = pts[:, None, :] - P.center[None, :, :2]
            local = np.einsum("nmj,mji->nmi", rel, P.rot[:, :2, :2])
            grown = P.half[:, :2] + ROBOT_RADIUS
            in_box = np.all(np.abs(local) <= grown, axis=2)
            in_ell = np.sum((local / grown) ** 2, axis=2) <= 1.0
            hit = np.where(P.shape[None, :] == BOX, in_box, in_ell)
            if hit.any():
                _, m = np.argwhere(hit)[0]
                raise ConfigError(field_name, f"segment {k} ({a[0]:.2f}, {a[1]:.2f}) -> ({b[0]:.2f}, {b[1]:.2f}) "
                                              f"passes through {CLASS_NAMES[P.label[m]]} '{P.names[m]}'")

    # ---- ray casting --------------------------------------------------------------------------
    def raycast(self, origin: np.ndarray, dirs: np.ndarray, max_range: float,
                dynamic: Primitives | None = None) -> tuple[np.ndarray, np.ndarray]:
        """First hit along each ray within ``max_range``.

        ``origin`` is ``(3,)`` (one sensor) or ``(n, 3)``; ``dirs`` are ``(n, 3)`` unit vectors.
        Returns ``ranges`` (inf where nothing is hit) and ``labels`` (0 where nothing is hit).
        """
        prims = self.static if dynamic is None or len(dynamic) == 0 else self.static.concat(dynamic)
        return cast_rays(prims, origin, dirs, max_range)

    # ---- ground truth -------------------------------------------------------------------------
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = self.static.aabb()
        return lo.min(0), hi.max(0)

    def gt_voxel_grid(self, resolution: float) -> VoxelGrid:
        """Semantic voxel grid of the static world, aligned to multiples of ``resolution``."""
        if not resolution > 0:
            raise ConfigError("resolution", f"must be positive, got {resolution}")
        lo, hi = self.bounds()
        lo, hi = lo - resolution, hi + resolution  # a margin of unknown cells all round
        origin = np.floor(lo / resolution - 1e-9) * resolution
        shape = tuple(int(v) for v in np.ceil((hi - origin) / resolution - 1e-9))
        labels = np.full(shape, -1, dtype=np.int8)
        grid = VoxelGrid(origin, resolution, labels)
        axes = [origin[a] + (np.arange(n) + 0.5) * resolution for a, n in enumerate(shape)]
        # interior of spaces is free
        zin = (axes[2] > self.floor_z) & (axes[2] < self.ceiling_z)
        for x0, y0, x1, y1 in self.rects:
            xi = (axes[0] > x0) & (axes[0] < x1)
            yi = (axes[1] > y0) & (axes[1] < y1)
            labels[np.ix_(xi, yi, zin)] = 0
        # structure, then door leaves and furniture, stamp their labels (later wins)
        P = self.static
        plo, phi = P.aabb()
        r2 = resolution / 2
        for m in range(len(P)):
            i0 = np.clip(np.floor((plo[m] - r2 - origin) / resolution).astype(int), 0, shape)
            i1 = np.clip(np.ceil((phi[m] + r2 - origin) / resolution).astype(int), 0, shape)
            sub = [a[s:e] for a, s, e in zip(axes, i0, i1, strict=True)]
            if any(len(s) == 0 for s in sub):
                continue
            c = np.stack(np.meshgrid(*sub, indexing="ij"), -1) - P.center[m]
            local = c @ P.rot[m]
            if P.shape[m] == BOX:
                inside = np.all(np.abs(local) < P.half[m] + r2 - 1e-9, axis=-1)
            else:
                inside = np.sum((local / (P.half[m] + r2)) ** 2, axis=-1) < 1.0
            block = labels[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]]
            block[inside] = P.label[m]
        return grid


def _cull(prims: Primitives, origin: np.ndarray, dirs: np.ndarray, max_range: float) -> np.ndarray:
    """Primitives whose bounding sphere may meet a ray from one origin: in range and in the cone."""
    radius = np.linalg.norm(prims.half, axis=1)
    rel = prims.center - origin
    dist = np.linalg.norm(rel, axis=1)
    keep = dist - radius <= max_range
    axis = dirs.mean(0)
    norm = np.linalg.norm(axis)
    if norm > 1e-6:
        axis = axis / norm
        half_angle = np.arccos(np.clip((dirs @ axis).min(), -1.0, 1.0))
        if half_angle < np.pi / 2:
            outside = dist > radius  # origin outside the sphere
            ang = np.arccos(np.clip((rel @ axis) / np.maximum(dist, 1e-12), -1.0, 1.0))
            slack = np.arcsin(np.clip(radius / np.maximum(dist, 1e-12), 0.0, 1.0))
            keep &= ~outside | (ang <= half_angle + slack)
    return keep


def cast_rays(prims: Primitives, origin: np.ndarray, dirs: np.ndarray,
              max_range: float) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised first-hit ray casting against boxes and ellipsoids (see :meth:`World.raycast`).

    Works on ``(primitives, rays)`` planes one local axis at a time, which keeps every numpy
    operation elementwise over large contiguous arrays (no reductions over tiny axes).
    """
    dirs = np.asarray(dirs, dtype=float)
    origin = np.asarray(origin, dtype=float)
    n = len(dirs)
    ranges = np.full(n, np.inf)
    labels = np.zeros(n, dtype=np.int16)
    if len(prims) == 0 or n == 0:
        return ranges, labels
    single = origin.ndim == 1
    keep = _cull(prims, origin, dirs, max_range) if single else np.ones(len(prims), dtype=bool)
    order = np.flatnonzero(keep)[np.argsort(prims.shape[keep], kind="stable")]  # boxes first
    nb = int(np.sum(prims.shape[order] == BOX))
    R, C, H, L = prims.rot[order], prims.center[order], prims.half[order], prims.label[order]
    if len(order) == 0:
        return ranges, labels
    if single:
        o_all = np.einsum("mj,mji->mi", origin - C, R)
    for s in range(0, n, _RAY_CHUNK):
        d = dirs[s:s + _RAY_CHUNK]
        if single:
            o_l = [o_all[:, i, None] for i in range(3)]
        else:
            rel = origin[s:s + _RAY_CHUNK].T[None] - C[:, :, None]  # (m, 3, n)
            o_l = [np.einsum("mjn,mj->mn", rel, R[:, :, i]) for i in range(3)]
        d_l = [R[:, 0, i, None] * d[:, 0] + R[:, 1, i, None] * d[:, 1] + R[:, 2, i, None] * d[:, 2]
               for i in range(3)]
        t = np.empty((len(L), len(d)))
        if nb:
            tnear = np.full((nb, len(d)), -np.inf)
            tfar = np.full((nb, len(d)), np.inf)
            for i in range(3):
                di = d_l[i][:nb]
                with np.errstate(divide="ignore"):
                    inv = 1.0 / np.where(np.abs(di) < 1e-12, np.copysign(1e-12, di), di)
                oi, hi = o_l[i][:nb], H[:nb, i, None]
                ta = (-hi - oi) * inv
                tb = (hi - oi) * inv
                np.maximum(tnear, np.minimum(ta, tb), out=tnear)
                np.minimum(tfar, np.maximum(ta, tb), out=tfar)
            t[:nb] = np.where((tfar >= tnear) & (tnear > 0), tnear, np.inf)
        if nb < len(L):
            he = H[nb:]
            oe = [o_l[i][nb:] / he[:, i, None] for i in range(3)]
            de = [d_l[i][nb:] / he[:, i, None] for i in range(3)]
            a = de[0] * de[0] + de[1] * de[1] + de[2] * de[2]
            b = oe[0] * de[0] + oe[1] * de[1] + oe[2] * de[2]
            c = oe[0] * oe[0] + oe[1] * oe[1] + oe[2] * oe[2] - 1.0
            disc = b * b - a * c
            with np.errstate(invalid="ignore"):
                root = (-b - np.sqrt(disc)) / a
            t[nb:] = np.where((disc >= 0) & (root > 0), root, np.inf)
        best = np.argmin(t, axis=0)
        tb_ = t[best, np.arange(len(d))]
        hit = tb_ <= max_range
        ranges[s:s + _RAY_CHUNK] = np.where(hit, tb_, np.inf)
        labels[s:s + _RAY_CHUNK] = np.where(hit, L[best], 0)
    return ranges, labels
