"""The ``kimera-multi query`` commands. ``cli/main.py`` calls :func:`register`.

``kimera-multi query RUN_DIR room-of O(3)``, ``... objects-in R(1) [--class chair]``,
``... path X,Y,Z X,Y,Z`` (or object / place names), ``... where ROBOT T``, and about people
``... people-in ROOM --at T``, ``... occupied-rooms --at T``, ``... where-was PERSON --at T``,
``... rooms-visited PERSON``. They read
``RUN_DIR/dsg.json``, or ``RUN_DIR/robotI/dsg.json`` with ``--robot I``; ``--json`` prints JSON
instead of a table (both options after the sub-command, or before RUN_DIR).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from kimera_multi_py.core.errors import KimeraMultiError

Robot = Annotated[int | None, typer.Option("--robot", help="Read RUN_DIR/robotI/dsg.json.")]
AsJson = Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")]
At = Annotated[float, typer.Option("--at", help="Time (s).")]
Within = Annotated[float, typer.Option("--within", help="A person counts when seen within this many s of --at.")]


def _graph_path(run_dir: Path, robot: int | None) -> Path:
    return run_dir / f"robot{robot}" / "dsg.json" if robot is not None else run_dir / "dsg.json"


def _point_or_name(text: str) -> Any:
    parts = text.split(",")
    if len(parts) == 3:
        try:
            return [float(p) for p in parts]
        except ValueError:
            pass
    return text


def _show(title: str, rows: list[dict[str, Any]], as_json: bool, payload: Any) -> None:
    if as_json:
        typer.echo(json.dumps(payload, indent=2))
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title)
    cols = list(rows[0]) if rows else ["result"]
    for c in cols:
        table.add_column(c)
    for r in rows:
        table.add_row(*[json.dumps(v) if isinstance(v, list) else ("-" if v is None else str(v)) for v in r.values()])
    if not rows:
        table.add_row("(none)")
    Console().print(table)


def _opts(ctx: typer.Context, robot: int | None, as_json: bool) -> tuple[Path, int | None, bool]:
    run_dir, r, j = ctx.obj
    return run_dir, robot if robot is not None else r, as_json or j


def _run(ctx: typer.Context, robot: int | None, as_json: bool, query: Any) -> tuple[Any, bool]:
    from kimera_multi_py.scene_graph.dsg_io import load_scene_graph

    run_dir, robot, as_json = _opts(ctx, robot, as_json)
    try:
        return query(load_scene_graph(_graph_path(run_dir, robot))), as_json
    except KimeraMultiError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(1) from None


def register(app: typer.Typer) -> None:
    """Add the ``query`` command group to ``app``."""
    from kimera_multi_py.scene_graph import queries

    query_app = typer.Typer(no_args_is_help=True, help="Ask a run's 3D scene graph (dsg.json).")
    app.add_typer(query_app, name="query")

    @query_app.callback()
    def _group(ctx: typer.Context,
               run_dir: Annotated[Path, typer.Argument(help="Run folder holding dsg.json (or robotI/dsg.json).")],
               robot: Robot = None, as_json: AsJson = False) -> None:
        """Ask a run's 3D scene graph (dsg.json)."""
        ctx.obj = (run_dir, robot, as_json)

    @query_app.command("room-of")
    def room_of(ctx: typer.Context, obj: Annotated[str, typer.Argument(help="Object, e.g. O(3) or 3.")],
                robot: Robot = None, as_json: AsJson = False) -> None:
        """The room of an object."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.room_of(g, obj))
        _show("room of object", [ans], as_json, ans)

    @query_app.command("objects-in")
    def objects_in(ctx: typer.Context, room: Annotated[str, typer.Argument(help="Room, e.g. R(1), 1 or meeting.")],
                   cls: Annotated[str | None, typer.Option("--class", help="Only this class.")] = None,
                   robot: Robot = None, as_json: AsJson = False) -> None:
        """The objects in a room, optionally of one class."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.objects_in(g, room, cls))
        _show(f"objects in {room}", ans, as_json, ans)

    @query_app.command("path")
    def path(ctx: typer.Context, start: Annotated[str, typer.Argument(help="X,Y,Z or O(k) or p(k).")],
             goal: Annotated[str, typer.Argument(help="X,Y,Z or O(k) or p(k).")],
             robot: Robot = None, as_json: AsJson = False) -> None:
        """The shortest route over places between two points."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.path(g, _point_or_name(start), _point_or_name(goal)))
        rows = [{"step": i, "waypoint": w} for i, w in enumerate(ans["waypoints"])]
        rows.append({"step": "length", "waypoint": round(ans["length"], 3)})
        rows.append({"step": "rooms", "waypoint": ans["rooms"]})
        _show(f"path ({len(ans['places'])} places)", rows, as_json, ans)

    @query_app.command("where")
    def where(ctx: typer.Context, robot_id: Annotated[str, typer.Argument(help="Robot index or letter.")],
              t: Annotated[float, typer.Argument(help="Time (s).")],
              robot: Robot = None, as_json: AsJson = False) -> None:
        """Where a robot was at time T: its keyframe, place and room."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.where(g, robot_id, t))
        _show(f"robot {robot_id} at t={t}", [ans], as_json, ans)

    @query_app.command("people-in")
    def people_in(ctx: typer.Context, room: Annotated[str, typer.Argument(help="Room, e.g. R(1), 1 or office.")],
                  at: At, within: Within = 1.0, robot: Robot = None, as_json: AsJson = False) -> None:
        """The people in a room at a time."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.people_in(g, room, at, within))
        _show(f"people in {room} at t={at}", ans, as_json, ans)

    @query_app.command("occupied-rooms")
    def occupied_rooms(ctx: typer.Context, at: At, within: Within = 1.0, robot: Robot = None,
                       as_json: AsJson = False) -> None:
        """The rooms with people in them at a time, and who."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.occupied_rooms(g, at, within))
        _show(f"occupied rooms at t={at}", ans, as_json, ans)

    @query_app.command("where-was")
    def where_was(ctx: typer.Context, person: Annotated[str, typer.Argument(help="Person, e.g. P(3) or 3.")],
                  at: At, robot: Robot = None, as_json: AsJson = False) -> None:
        """Where a person was at a time: position, place and room."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.where_was(g, person, at))
        _show(f"{person} at t={at}", [ans], as_json, ans)

    @query_app.command("rooms-visited")
    def rooms_visited(ctx: typer.Context, person: Annotated[str, typer.Argument(help="Person, e.g. P(3) or 3.")],
                      robot: Robot = None, as_json: AsJson = False) -> None:
        """The rooms a person was seen in, visit by visit."""
        ans, as_json = _run(ctx, robot, as_json, lambda g: queries.rooms_visited(g, person))
        _show(f"rooms visited by {person}", ans, as_json, ans)
