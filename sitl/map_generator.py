"""Random building maps, so exploration is tried on maps nobody tuned it for.

Rooms by recursive division of a rectangle: each dividing wall gets a door (sometimes two), so
every room is reachable, and a later wall never ends in an earlier wall's door. Furniture (boxes
at any angle) stands in the rooms, clear of their walls, doors and each other by a passage the
vehicle fits through. The map is checked before it is returned: its free space, shrunk by the
vehicle's berth, is one piece holding the start, so every room can be flown to. Deterministic
for a seed; written in the format of ``config/maps/README.md``.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import mapping

from sitl.errors import MapError
from sitl.world import MAX_SIDE_M


@dataclass(frozen=True, slots=True)
class MapGenParams:
    """The building's size and what goes in it; metres."""

    width_m: float = 24.0
    height_m: float = 16.0
    min_room_m: float = 3.5  # no room narrower than this
    split_chance: float = 0.85  # a room that may be divided is, with this chance
    wall_m: float = 0.15
    door_min_m: float = 1.0
    door_max_m: float = 1.4
    second_door_chance: float = 0.25
    furniture_max_per_room: int = 2
    furniture_min_m: float = 0.4
    furniture_max_m: float = 1.6
    passage_m: float = 1.1  # furniture keeps this from walls, doors and other furniture
    berth_m: float = 0.35  # the vehicle's radius and margin: every room must be reachable with it
    attempts: int = 50


@dataclass(frozen=True, slots=True)
class _Door:
    horizontal: bool  # in a wall along x (at y = at_m), else along y (at x = at_m)
    at_m: float
    lo_m: float
    hi_m: float


def generate_map(seed: int, params: MapGenParams | None = None) -> dict[str, Any]:
    """A GeoJSON FeatureCollection of a random building (see the module docstring)."""
    p = params or MapGenParams()
    if not (math.isfinite(p.width_m) and math.isfinite(p.height_m)):
        raise MapError("map generator: width and height must be finite")
    if p.width_m < p.min_room_m or p.height_m < p.min_room_m:
        raise MapError(f"map generator: the building must be at least {p.min_room_m:g} m each way (one room)")
    if max(p.width_m, p.height_m) > MAX_SIDE_M:
        raise MapError(f"map generator: the building must be at most {MAX_SIDE_M:g} m each way (the simulator's limit)")
    if not (0.0 < p.door_min_m <= p.door_max_m):
        raise MapError(f"map generator: doors must be 0 < min <= max wide, got {p.door_min_m:g}-{p.door_max_m:g} m")
    if p.furniture_max_per_room < 0:
        raise MapError(f"map generator: furniture per room must be >= 0, got {p.furniture_max_per_room}")
    if p.min_room_m < 2 * p.door_max_m:
        raise MapError("map generator: a room's wall must fit two doors")
    rng = np.random.default_rng(seed)
    for _ in range(p.attempts):
        walls, rooms, doors = _divide(rng, p)
        furniture = _furnish(rng, p, rooms, doors)
        boundary = shapely.box(0.0, 0.0, p.width_m, p.height_m)
        obstacles = walls + furniture
        free = boundary.difference(shapely.union_all(obstacles)) if obstacles else boundary
        start = _start(rng, p, rooms, free)
        if start is not None and _all_reachable(free, start, p.berth_m):
            return _geojson(seed, p, boundary, obstacles, start, float(rng.uniform(-180.0, 180.0)), len(rooms))
    raise MapError(f"map generator: no valid map for seed {seed} in {p.attempts} attempts")


def write_generated_map(path: Path, seed: int, params: MapGenParams | None = None) -> dict[str, Any]:
    """:func:`generate_map`, written to ``path`` (its folder made if missing); returns the map."""
    data = generate_map(seed, params)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1) + "\n")
    return data


def _divide(
    rng: np.random.Generator, p: MapGenParams
) -> tuple[list[shapely.Polygon], list[tuple[float, float, float, float]], list[_Door]]:
    """Recursive division: the wall pieces, the leaf rooms (x0, y0, x1, y1) and the doors."""
    walls: list[shapely.Polygon] = []
    doors: list[_Door] = []
    rooms: list[tuple[float, float, float, float]] = []
    todo = [(0.0, 0.0, p.width_m, p.height_m)]
    while todo:
        x0, y0, x1, y1 = todo.pop()
        w, h = x1 - x0, y1 - y0
        vertical = w >= h  # divide across the longer side
        span = w if vertical else h
        first = not walls  # the building itself is always divided
        if span < 2 * p.min_room_m or (not first and rng.random() > p.split_chance):
            rooms.append((x0, y0, x1, y1))
            continue
        at = _split_at(rng, p, doors, vertical, (x0, y0, x1, y1))
        if at is None:
            rooms.append((x0, y0, x1, y1))
            continue
        lo, hi = (y0, y1) if vertical else (x0, x1)
        gaps = _doors_in(rng, p, lo, hi)
        doors.extend(_Door(not vertical, at, a, b) for a, b in gaps)
        edges = [lo, *[v for gap in gaps for v in gap], hi]
        half = p.wall_m / 2.0
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            if b - a > 1e-6:
                box = shapely.box(at - half, a, at + half, b) if vertical else shapely.box(a, at - half, b, at + half)
                walls.append(box)
        if vertical:
            todo += [(x0, y0, at, y1), (at, y0, x1, y1)]
        else:
            todo += [(x0, y0, x1, at), (x0, at, x1, y1)]
    return walls, rooms, doors


def _split_at(
    rng: np.random.Generator,
    p: MapGenParams,
    doors: list[_Door],
    vertical: bool,
    room: tuple[float, float, float, float],
) -> float | None:
    """Where to divide the room: leaving rooms no narrower than ``min_room_m``, and not where
    the new wall would end in a door of the walls it meets."""
    x0, y0, x1, y1 = room
    lo, hi = (x0, x1) if vertical else (y0, y1)
    ends = (y0, y1) if vertical else (x0, x1)
    keep = p.wall_m / 2.0 + 0.3
    for _ in range(20):
        at = float(rng.uniform(lo + p.min_room_m, hi - p.min_room_m))
        blocked = any(
            d.horizontal == vertical
            and any(abs(d.at_m - e) < 1e-6 for e in ends)
            and d.lo_m - keep < at < d.hi_m + keep
            for d in doors
        )
        if not blocked:
            return round(at, 2)
    return None


def _doors_in(rng: np.random.Generator, p: MapGenParams, lo: float, hi: float) -> list[tuple[float, float]]:
    """One door (sometimes two) along a wall from ``lo`` to ``hi``: (start, end) each, sorted."""
    count = 2 if rng.random() < p.second_door_chance and hi - lo >= 4 * p.door_max_m else 1
    slots = np.linspace(lo, hi, count + 1)
    out = []
    for a, b in itertools.pairwise(slots):
        width = float(rng.uniform(p.door_min_m, p.door_max_m))
        start = float(rng.uniform(a + 0.3, b - 0.3 - width))
        out.append((round(start, 2), round(start + width, 2)))
    return out


def _furnish(
    rng: np.random.Generator, p: MapGenParams, rooms: list[tuple[float, float, float, float]], doors: list[_Door]
) -> list[shapely.Polygon]:
    """Boxes at any angle in the rooms, each ``passage_m`` clear of walls, doors and each other."""
    out: list[shapely.Polygon] = []
    door_zones = [
        shapely.box(d.lo_m, d.at_m - 1.0, d.hi_m, d.at_m + 1.0)
        if d.horizontal
        else shapely.box(d.at_m - 1.0, d.lo_m, d.at_m + 1.0, d.hi_m)
        for d in doors
    ]
    for x0, y0, x1, y1 in rooms:
        inner = shapely.box(x0, y0, x1, y1).buffer(-(p.passage_m + p.wall_m / 2.0), join_style="mitre")
        wanted, placed = int(rng.integers(0, p.furniture_max_per_room + 1)), 0
        for _ in range(10 * wanted):
            if inner.is_empty or placed == wanted:
                break
            a, b = rng.uniform(p.furniture_min_m, p.furniture_max_m, size=2)
            ix0, iy0, ix1, iy1 = inner.bounds
            centre = rng.uniform((ix0, iy0), (ix1, iy1))
            angle = float(rng.uniform(0.0, math.pi))
            c, s = math.cos(angle), math.sin(angle)
            corners = np.array([(-a, -b), (a, -b), (a, b), (-a, b)]) / 2.0 @ np.array([[c, s], [-s, c]]) + centre
            box = shapely.Polygon(corners)
            clear = box.buffer(p.passage_m)
            if not inner.contains(box) or any(clear.intersects(z) for z in door_zones):
                continue
            if any(clear.intersects(o) for o in out):
                continue
            out.append(shapely.Polygon(np.round(corners, 3)))
            placed += 1
    return out


def _start(
    rng: np.random.Generator, p: MapGenParams, rooms: list[tuple[float, float, float, float]], free: shapely.Geometry
) -> tuple[float, float] | None:
    """The centre of a random room, if the vehicle fits there."""
    x0, y0, x1, y1 = rooms[int(rng.integers(0, len(rooms)))]
    point = shapely.Point((x0 + x1) / 2.0, (y0 + y1) / 2.0)
    if not free.contains(point) or free.boundary.distance(point) < 2.0 * p.berth_m:
        return None
    return (round(point.x, 2), round(point.y, 2))


def _all_reachable(free: shapely.Geometry, start: tuple[float, float], berth_m: float) -> bool:
    """Whether the free space the vehicle's centre may take (``berth_m`` off every wall) is one
    piece, holding the start: no room or corner it could see is out of its reach."""
    core = free.buffer(-berth_m)
    parts = list(getattr(core, "geoms", [core]))
    return len(parts) == 1 and core.contains(shapely.Point(start))


def _geojson(
    seed: int,
    p: MapGenParams,
    boundary: shapely.Polygon,
    obstacles: list[shapely.Polygon],
    start: tuple[float, float],
    yaw_deg: float,
    rooms: int,
) -> dict[str, Any]:
    def feature(kind: str, geom: shapely.Geometry, **props: float) -> dict[str, Any]:
        return {"type": "Feature", "properties": {"kind": kind, **props}, "geometry": mapping(geom)}

    size = f"{p.width_m:g} x {p.height_m:g} m"
    doors = f"doors {p.door_min_m:g}-{p.door_max_m:g} m"
    return {
        "type": "FeatureCollection",
        "name": f"generated-{seed}",
        "description": f"generated (seed {seed}): {size}, {rooms} room{'' if rooms == 1 else 's'} by recursive "
        f"division, {doors}, furniture",
        "features": [
            feature("boundary", boundary),
            *(feature("obstacle", o) for o in obstacles),
            feature("start", shapely.Point(start), yaw_deg=round(yaw_deg, 1)),
        ],
    }
