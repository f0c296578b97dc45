"""Procedural buildings: scenarios nobody tuned for (see docs/simulator.md, generated buildings).

:func:`generate_building` lays out one or more parallel east-west corridors with a row of rooms
on each side (rooms of several widths; a row's depth per side of the corridors), a door between
each room and its corridor, and optional open halls at the ends of the corridors that join them
(without halls, a connector corridor at the west end joins several corridors). Some layouts are
repeated ``repeat`` times -- identical rooms of one size, door and furniture, side by side or
scattered along rows facing the same way -- while every other room gets its own furniture
(:mod:`kimera_multi_py.sim.furnish`) with a distinct object set where it can. Robots start in
different places and their routes overlap: every robot visits a shared non-repeated place (a
hall, or a distinct room) and copies of the repeated rooms. People can walk the corridors and
halls.

The same arguments give the same scenario and, through :func:`scenario_toml`, the same bytes
(all draws come from numpy's PCG64 generator seeded with ``(seed, attempt)``).
Every generated scenario passes the simulator's own checks (:meth:`World.plan_route`,
:meth:`World.check_path`); a draw that does not is drawn again from the next attempt's stream.
Which places are repeats is in the layout names: :func:`repeated_layouts` lists the identical
rooms and :func:`distinct_places` the non-repeated spaces each robot's route visits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.sim.furnish import ROOM_KINDS, Opening, furnish, signature
from kimera_multi_py.sim.scenario import (
    DoorConfig,
    HumanConfig,
    LayoutConfig,
    OdometryConfig,
    RobotConfig,
    ScenarioConfig,
    SpaceConfig,
    check_references,
)
from kimera_multi_py.sim.world import World

MAX_ROBOTS = 26
ATTEMPTS = 8


@dataclass
class _Room:
    name: str
    layout: str
    kind: str
    width: float
    side: str  # "S": south of its corridor (door on its north wall), "N": north of it
    door_at: float  # along the door wall, from the room's min x
    group: int | None = None  # repeat group, or None for a room with its own layout
    row: int = -1
    x0: float = 0.0


@dataclass
class _Plan:
    rows: list[list[_Room]] = field(default_factory=list)
    spaces: list[SpaceConfig] = field(default_factory=list)
    doors: list[DoorConfig] = field(default_factory=list)
    layouts: dict[str, LayoutConfig] = field(default_factory=dict)
    corridor_of: dict[str, int] = field(default_factory=dict)  # place -> corridor index (halls: -1)
    junctions: list[float] = field(default_factory=list)  # x of spaces joining the corridors


def _r(x: float, step: float = 0.1) -> float:
    return round(round(float(x) / step) * step, 2)


def _pick(rng: np.random.Generator, *values: float) -> float:
    return float(values[int(rng.integers(len(values)))])


def _check_args(seed: int, rooms: int, repeat: int, robots: int, halls: int, people: int, corridors: int,
                groups: int, visits: int) -> None:
    checks = [
        ("seed", seed >= 0, f"must be >= 0, got {seed}"),
        ("rooms", 1 <= rooms <= 60, f"must be 1..60, got {rooms}"),
        ("repeat", 0 <= repeat <= 12, f"must be 0..12 (0 or 1: no repeats), got {repeat}"),
        ("groups", 0 <= groups <= len(ROOM_KINDS), f"must be 0..{len(ROOM_KINDS)}, got {groups}"),
        ("repeat", repeat < 2 or groups * repeat <= rooms,
         f"{groups} group(s) of {repeat} identical rooms need at least {groups * repeat} rooms, got {rooms}"),
        ("robots", 1 <= robots <= MAX_ROBOTS, f"must be 1..{MAX_ROBOTS}, got {robots}"),
        ("robots", robots <= rooms + halls, f"{robots} robots need as many start places; there are "
                                            f"{rooms} rooms and {halls} halls"),
        ("halls", 0 <= halls <= 2, f"must be 0..2, got {halls}"),
        ("people", 0 <= people <= 20, f"must be 0..20, got {people}"),
        ("corridors", 1 <= corridors <= 4, f"must be 1..4, got {corridors}"),
        ("visits", 1 <= visits <= 12, f"must be 1..12, got {visits}"),
    ]
    for name, ok, problem in checks:
        if not ok:
            raise ConfigError(name, problem)


def _rooms(rng: np.random.Generator, rooms: int, repeat: int, groups: int) -> list[_Room]:
    """The rooms to place: ``groups`` x ``repeat`` identical ones, then the distinct ones."""
    out: list[_Room] = []
    n_groups = groups if repeat >= 2 else 0
    kinds = [str(k) for k in rng.permutation(ROOM_KINDS)]
    first_side = str(rng.choice(["S", "N"]))
    for g in range(n_groups):
        kind, width = kinds[g], _pick(rng, 4.5, 5.0, 5.5, 6.0)
        side = first_side if g % 2 == 0 else ("N" if first_side == "S" else "S")
        door_at = _r(rng.uniform(1.2, width - 1.2), 0.5)
        for k in range(repeat):
            out.append(_Room(f"{kind}_{chr(97 + k)}", kind, kind, width, side, door_at, group=g))
    order = kinds[n_groups:] or kinds  # distinct rooms: kinds other than the repeated ones
    for i in range(rooms - n_groups * repeat):
        kind = order[i % len(order)]
        width = _pick(rng, 4.0, 4.5, 5.0, 6.0, 7.0, 8.0)
        name = f"{kind}_{i + 1}"
        out.append(_Room(name, name, kind, width, str(rng.choice(["S", "N"])), 0.0))
    return out


def _rows(rng: np.random.Generator, rooms: list[_Room], corridors: int, scatter: bool) -> list[list[_Room]]:
    """Rooms into rows (``2c``: south of corridor c, ``2c + 1``: north of it), west to east."""
    rows: list[list[list[_Room]]] = [[] for _ in range(2 * corridors)]  # entries: blocks of rooms
    length = [0.0] * len(rows)
    groups = sorted({r.group for r in rooms if r.group is not None})
    for g in groups:
        copies = [r for r in rooms if r.group == g]
        side_rows = [i for i in range(len(rows)) if (i % 2 == 0) == (copies[0].side == "S")]
        if scatter:
            start = int(rng.integers(len(side_rows)))
            for k, room in enumerate(copies):
                i = side_rows[(start + k) % len(side_rows)]
                rows[i].append([room])
                length[i] += room.width
        else:
            i = side_rows[int(rng.integers(len(side_rows)))]
            rows[i].append(copies)
            length[i] += sum(r.width for r in copies)
    for room in (r for r in rooms if r.group is None):
        i = int(np.argmin(length))
        room.side = "S" if i % 2 == 0 else "N"
        rows[i].append([room])
        length[i] += room.width
    out = []
    for entries in rows:
        order = list(rng.permutation(len(entries)))
        for _ in range(20):  # scattered copies: not next to each other where the row allows it
            flat = [entries[j][0].group for j in order]
            if not any(a is not None and a == b for a, b in zip(flat, flat[1:], strict=False)):
                break
            order = list(rng.permutation(len(entries)))
        out.append([room for j in order for room in entries[j]])
    copies_seen: dict[int, int] = {}
    for room in (r for row in out for r in row if r.group is not None):  # copies a, b, ... in row order
        k = copies_seen[room.group] = copies_seen.get(room.group, -1) + 1
        room.name = f"{room.kind}_{chr(97 + k)}"
    return out


def _stretch(rows: list[list[_Room]], max_width: float = 9.0) -> float:
    """Widen the distinct rooms of short rows towards the longest row; the corridors' length."""
    total = max([6.0] + [sum(r.width for r in row) for row in rows])
    for row in rows:
        free = [r for r in row if r.group is None]
        extra = total - sum(r.width for r in row)
        for k, room in enumerate(free):
            add = min(_r(extra / (len(free) - k), 0.1), max_width - room.width)
            if add > 0:
                room.width = _r(room.width + add, 0.1)
                extra -= add
    return total


def _building(rng: np.random.Generator, rooms: list[_Room], corridors: int, halls: int,
              scatter: bool) -> _Plan:
    plan = _Plan(rows=_rows(rng, rooms, corridors, scatter))
    length = _stretch(plan.rows)
    cw = _pick(rng, 2.0, 2.2, 2.4)
    depth = {"S": _pick(rng, 4.5, 5.0, 5.5, 6.0), "N": _pick(rng, 4.5, 5.0, 5.5, 6.0)}
    y = 0.0
    corridor_y: list[tuple[float, float]] = []
    for c in range(corridors):
        bands = {"S": (y, _r(y + depth["S"])), "N": (_r(y + depth["S"] + cw), _r(y + depth["S"] + cw + depth["N"]))}
        cy = (bands["S"][1], bands["N"][0])
        corridor_y.append(cy)
        cname = "corridor" if corridors == 1 else f"corridor_{c}"
        plan.spaces.append(SpaceConfig(name=cname, kind="corridor", min=(0.0, cy[0]), max=(_r(length), cy[1])))
        for side in ("S", "N"):
            x = 0.0
            for room in plan.rows[2 * c + (side == "N")]:
                room.x0, room.row = x, 2 * c + (side == "N")
                y0, y1 = bands[side]
                plan.spaces.append(SpaceConfig(name=room.name, min=(x, y0), max=(_r(x + room.width), y1),
                                               layout=room.layout))
                if room.group is None:
                    room.door_at = _r(rng.uniform(1.0, room.width - 1.0), 0.1)
                plan.doors.append(DoorConfig(at=(_r(x + room.door_at), cy[1] if side == "N" else cy[0])))
                plan.corridor_of[room.name] = c
                x = _r(x + room.width)
        y = bands["N"][1]
    top = y
    mids = [_r((a + b) / 2, 0.05) for a, b in corridor_y]
    opening = _r(cw - 0.4)
    for h in range(halls):
        hw = _pick(rng, 7.0, 8.0, 9.0, 10.0)
        east = h == 0
        name = "hall_east" if east else "hall_west"
        x0, x1 = (_r(length), _r(length + hw)) if east else (-hw, 0.0)
        plan.spaces.append(SpaceConfig(name=name, min=(x0, 0.0), max=(x1, top), layout=name))
        plan.doors += [DoorConfig(at=(x0 if east else x1, m), width=opening, leaf=False) for m in mids]
        plan.layouts[name] = furnish(rng, "hall", (hw, top), [Opening("W" if east else "E", m, opening, False)
                                                             for m in mids], tour_points=6)
        plan.corridor_of[name] = -1
        plan.junctions.append(x0 if east else x1)
    if halls == 0 and corridors > 1:
        plan.spaces.append(SpaceConfig(name="connector", kind="corridor", min=(-cw, corridor_y[0][0]),
                                       max=(0.0, corridor_y[-1][1])))
        plan.doors += [DoorConfig(at=(0.0, m), width=opening, leaf=False) for m in mids]
        plan.junctions.append(0.0)
    _furnish_rooms(rng, plan, depth)
    return plan


def _furnish_rooms(rng: np.random.Generator, plan: _Plan, depth: dict[str, float]) -> None:
    seen: set[tuple[tuple[str, int], ...]] = set()
    for row in plan.rows:
        for room in row:
            if room.layout in plan.layouts:
                continue
            size = (room.width, depth[room.side])
            opening = Opening("N" if room.side == "S" else "S", room.door_at)
            points = int(rng.integers(3, 6))
            for _ in range(8):  # a distinct object set where the draws allow one
                layout = furnish(rng, room.kind, size, [opening], tour_points=points)
                if signature(layout) not in seen:
                    break
            seen.add(signature(layout))
            plan.layouts[room.layout] = layout


def _centre(space: SpaceConfig) -> np.ndarray:
    return (np.array(space.min) + np.array(space.max)) / 2


def _travel(plan: _Plan, a: str, b: str) -> float:
    """Rough walking distance between two places: along the corridors, via a junction if needed."""
    sp = {s.name: s for s in plan.spaces}
    pa, pb = _centre(sp[a]), _centre(sp[b])
    ca, cb = plan.corridor_of[a], plan.corridor_of[b]
    if ca == cb or ca < 0 or cb < 0 or not plan.junctions:
        return float(np.abs(pa - pb).sum())
    return float(min(abs(pa[0] - x) + abs(pb[0] - x) for x in plan.junctions) + abs(pa[1] - pb[1]))


def _routes(rng: np.random.Generator, plan: _Plan, robots: int, visits: int) -> list[RobotConfig]:
    places = [r.name for row in plan.rows for r in row] + [n for n, c in plan.corridor_of.items() if c < 0]
    sp = {s.name: s for s in plan.spaces}
    uses = {n: sum(s.layout == sp[n].layout for s in plan.spaces) for n in places}
    unique = [p for p in places if uses[p] == 1]
    copies: dict[str, list[str]] = {}
    for p in places:
        if uses[p] > 1:
            copies.setdefault(str(sp[p].layout), []).append(p)
    by_x = sorted(places, key=lambda p: (float(_centre(sp[p])[0]), float(_centre(sp[p])[1])))
    u = rng.uniform()
    starts = [by_x[int((k + u) * len(by_x) / robots)] for k in range(robots)]
    mid = float(np.mean([_centre(sp[p])[0] for p in places]))
    shared = next((p for p in unique if plan.corridor_of[p] < 0), None)
    if shared is None and unique:
        spare = [p for p in unique if p not in starts] or unique
        shared = min(spare, key=lambda p: abs(float(_centre(sp[p])[0]) - mid))
    groups = sorted(copies)
    out = []
    chosen: list[list[str]] = []
    for i in range(robots):
        own = [starts[i]]
        want = [shared] if shared else []
        if groups:
            group = copies[groups[i % len(groups)]]
            want += [group[i % len(group)], group[(i + 1) % len(group)]]
        for p in want:
            if p is not None and p not in own and len(own) < visits:
                own.append(p)
        others = sorted({p for route in chosen for p in route} - set(own))
        while len(own) < visits:
            pool = others if others and rng.random() < 0.6 else [p for p in places if p not in own]
            if not pool:
                break
            pick = pool[int(rng.integers(len(pool)))]
            own.append(pick)
            others = [p for p in others if p != pick]
        route, rest = [own[0]], own[1:]
        while rest:  # nearest next place, so routes sweep the building instead of zig-zagging
            nxt = min(rest, key=lambda p: _travel(plan, route[-1], p))
            route.append(nxt)
            rest.remove(nxt)
        chosen.append(route)
        out.append(RobotConfig(route=route))
    return out


def _humans(rng: np.random.Generator, plan: _Plan, people: int) -> list[HumanConfig]:
    lanes: list[tuple[tuple[float, float], tuple[float, float], float]] = []  # start, end, max offset
    sp = {s.name: s for s in plan.spaces}
    halls = [n for n, c in plan.corridor_of.items() if c < 0]
    corridors = [s for s in plan.spaces if s.kind == "corridor" and s.name != "connector"]
    for k in range(max(len(corridors), len(halls))):
        if k < len(corridors):
            c = corridors[k]
            ym = (c.min[1] + c.max[1]) / 2
            lanes.append(((c.min[0] + 0.8, ym), (c.max[0] - 0.8, ym), 0.4))
        if k < len(halls):
            h = sp[halls[k]]
            x = h.min[0] + 0.9 if halls[k] == "hall_east" else h.max[0] - 0.9
            lanes.append(((x, h.min[1] + 1.0), (x, h.max[1] - 1.0), 0.2))
    out = []
    for p in range(people):
        (a, b, span), rnd = lanes[p % len(lanes)], p // len(lanes)
        off = span * (0.0 if rnd == 0 else (1 if rnd % 2 else -1) / ((rnd + 1) // 2))
        vertical = a[0] == b[0]
        shift = (off, 0.0) if vertical else (0.0, off)
        ends = [(_r(a[0] + shift[0], 0.05), _r(a[1] + shift[1], 0.05)),
                (_r(b[0] + shift[0], 0.05), _r(b[1] + shift[1], 0.05))]
        out.append(HumanConfig(waypoints=ends if p % 2 == 0 else ends[::-1], speed=_pick(rng, 0.6, 0.8, 1.0)))
    return out


def _valid(cfg: ScenarioConfig) -> bool:
    """The simulator's own checks: references, doors on shared walls, routes clear of obstacles."""
    try:
        check_references(cfg)
        world = World(cfg)
        for i, robot in enumerate(cfg.robots):
            world.check_path(world.plan_route(list(robot.route or []), f"robots[{i}].route"), f"robots[{i}]")
        for i, h in enumerate(cfg.humans):
            world.check_path(np.asarray(h.waypoints, dtype=float), f"humans[{i}].waypoints")
    except ConfigError:
        return False
    return True


def generate_building(seed: int, rooms: int = 8, repeat: int = 3, robots: int = 3, halls: int = 1,
                      people: int = 0, corridors: int = 1, groups: int = 1, visits: int = 4,
                      scatter: bool | None = None, name: str | None = None) -> ScenarioConfig:
    """A random valid office building; the same arguments give the same scenario.

    ``rooms`` rooms along ``corridors`` corridors, of which ``groups`` x ``repeat`` are identical
    (``repeat`` < 2: none), side by side or, with ``scatter`` (default: drawn from the seed),
    spread along the rows facing the same way; ``halls`` open halls (0..2) at the corridors' ends;
    ``robots`` robots starting in different places, each visiting ``visits`` places (its start,
    the shared distinct place, copies of the repeated rooms, then places others visit);
    ``people`` people walking the corridors and halls. Bad arguments raise :class:`ConfigError`.
    """
    _check_args(seed, rooms, repeat, robots, halls, people, corridors, groups, visits)
    for attempt in range(ATTEMPTS):
        rng = np.random.default_rng([seed, attempt])
        spread = bool(rng.random() < 0.5) if scatter is None else scatter
        plan = _building(rng, _rooms(rng, rooms, repeat, groups), corridors, halls, spread)
        cfg = ScenarioConfig(
            name=name or f"generated_{seed}", seed=0, spaces=plan.spaces, doors=plan.doors,
            layouts=dict(sorted(plan.layouts.items())), robots=_routes(rng, plan, robots, visits),
            humans=_humans(rng, plan, people), odometry=OdometryConfig(rot_sigma_deg=0.15, trans_sigma=0.02))
        if _valid(cfg):
            return cfg
    raise ConfigError("seed", f"no valid building in {ATTEMPTS} attempts for seed {seed}")  # pragma: no cover


def repeated_layouts(cfg: ScenarioConfig) -> dict[str, list[str]]:
    """Layouts used by more than one space (identical places), with those spaces in file order."""
    spaces: dict[str, list[str]] = {}
    for s in cfg.spaces:
        if s.layout is not None:
            spaces.setdefault(s.layout, []).append(s.name)
    return {k: v for k, v in spaces.items() if len(v) > 1}


def distinct_places(cfg: ScenarioConfig) -> dict[int, set[str]]:
    """Robot index -> the spaces its route visits whose layout no other space uses.

    Routes count the spaces they name; a robot following waypoints counts the spaces its
    waypoints lie in. Spaces without a layout (bare corridors) are not places.
    """
    counts: dict[str, int] = {}
    for s in cfg.spaces:
        if s.layout is not None:
            counts[s.layout] = counts.get(s.layout, 0) + 1
    once = {s.name for s in cfg.spaces if s.layout is not None and counts[s.layout] == 1}
    out: dict[int, set[str]] = {}
    for i, robot in enumerate(cfg.robots):
        if robot.route is not None:
            visited = set(robot.route)
        else:
            visited = {s.name for s in cfg.spaces for p in robot.waypoints or []
                       if s.min[0] <= p[0] <= s.max[0] and s.min[1] <= p[1] <= s.max[1]}
        out[i] = visited & once
    return out


def describe(cfg: ScenarioConfig) -> list[str]:
    """Comment lines for a generated file: the identical rooms and each robot's distinct places."""
    lines = [f"{len(cfg.spaces)} spaces, {len(cfg.doors)} doors, {len(cfg.robots)} robots, "
             f"{len(cfg.humans)} people."]
    reps = repeated_layouts(cfg)
    lines += [f"Identical rooms (layout {k!r}): {', '.join(v)}." for k, v in reps.items()] or ["No identical rooms."]
    for robot, places in distinct_places(cfg).items():
        lines.append(f"Robot {robot} visits distinct places: {', '.join(sorted(places)) or '(none)'}.")
    return lines
