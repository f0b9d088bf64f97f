"""Maps: GeoJSON FeatureCollections in a local metric frame (x east, y north, metres).

See config/maps/README.md: one ``boundary`` Polygon, any number of ``obstacle`` Polygons, one
``start`` Point with ``yaw_deg``.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import shape as geojson_shape

from companion.core.geometry import FloatArray, Pose2, point_segment_distances
from sitl.errors import MapError

# The simulator's largest map, per side: its ground-truth coverage grid has 0.2 m cells and the
# grid baseline's 0.1 m cells, so memory grows with the area (a 100 km square asked for 1.8 TiB).
# A building, even a campus (60 x 40 m), is well within it.
MAX_SIDE_M = 200.0


@dataclass(frozen=True)
class World:
    """The true world: free space, the wall segments that bound it, and the start pose."""

    name: str
    boundary: shapely.Polygon
    obstacles: tuple[shapely.Polygon, ...]
    free: shapely.Geometry
    start: Pose2
    walls: FloatArray  # (M, 2, 2) segments: the boundary ring and every obstacle ring

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        minx, miny, maxx, maxy = self.boundary.bounds
        return (float(minx), float(miny), float(maxx), float(maxy))

    def clearance_at(self, x_m: float, y_m: float) -> float:
        """Distance from a point to the nearest wall."""
        return float(point_segment_distances(np.array([[x_m, y_m]]), self.walls).min())


def _ring_segments(ring: Any) -> FloatArray:
    c = np.asarray(ring.coords, dtype=np.float64)
    return np.stack((c[:-1], c[1:]), axis=1)


def _polygon(feature: dict[str, Any], path: Path, what: str) -> shapely.Polygon:
    try:
        with warnings.catch_warnings():  # a NaN coordinate warns first; is_valid_reason names it below
            warnings.simplefilter("ignore", RuntimeWarning)
            geom = geojson_shape(feature["geometry"])
    except Exception as exc:  # shapely raises several types for bad GeoJSON
        raise MapError(f"{path}: {what} has an unreadable geometry ({exc})") from None
    if not isinstance(geom, shapely.Polygon):
        raise MapError(f"{path}: {what} must be a Polygon, got {geom.geom_type}")
    if geom.is_empty or not geom.is_valid:
        reason = shapely.is_valid_reason(geom)
        raise MapError(f"{path}: {what} is not a valid polygon ({reason})")
    return geom


def load_world(path: str | Path) -> World:
    """Read and check a map file; every problem is a :class:`MapError` naming the file."""
    p = Path(path)
    try:
        data = json.loads(p.read_text())
    except FileNotFoundError:
        raise MapError(f"{p}: no such map file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapError(f"{p}: cannot read ({exc})") from None
    except json.JSONDecodeError as exc:
        raise MapError(f"{p}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict) or data.get("type") != "FeatureCollection":
        raise MapError(f"{p}: must be a GeoJSON FeatureCollection")
    features = data.get("features")
    if not isinstance(features, list):
        raise MapError(f"{p}: 'features' must be a list")
    boundaries, obstacles, starts = [], [], []
    for i, f in enumerate(features):
        if not isinstance(f, dict) or not isinstance(f.get("properties"), dict):
            raise MapError(f"{p}: feature {i} has no properties")
        kind = f["properties"].get("kind")
        if kind == "boundary":
            boundaries.append(_polygon(f, p, "boundary"))
        elif kind == "obstacle":
            obstacles.append(_polygon(f, p, f"obstacle (feature {i})"))
        elif kind == "start":
            starts.append((i, f))
        else:
            raise MapError(f"{p}: feature {i} has unknown kind {kind!r} (boundary, obstacle, start)")
    if len(boundaries) != 1:
        raise MapError(f"{p}: needs exactly one boundary, found {len(boundaries)}")
    if len(starts) != 1:
        raise MapError(f"{p}: needs exactly one start, found {len(starts)}")
    minx, miny, maxx, maxy = boundaries[0].bounds
    if max(maxx - minx, maxy - miny) > MAX_SIDE_M:
        raise MapError(
            f"{p}: the boundary spans {maxx - minx:g} x {maxy - miny:g} m; the simulator takes maps up to "
            f"{MAX_SIDE_M:g} m a side (its coverage grids grow with the area)"
        )
    i, sf = starts[0]
    try:
        pt = geojson_shape(sf["geometry"])
    except Exception as exc:
        raise MapError(f"{p}: start has an unreadable geometry ({exc})") from None
    if not isinstance(pt, shapely.Point):
        raise MapError(f"{p}: start must be a Point, got {pt.geom_type}")
    yaw_deg = sf["properties"].get("yaw_deg", 0.0)
    if not isinstance(yaw_deg, int | float) or not math.isfinite(yaw_deg):
        raise MapError(f"{p}: start yaw_deg must be a finite number, got {yaw_deg!r}")
    boundary = boundaries[0]
    free = boundary.difference(shapely.union_all(obstacles)) if obstacles else boundary
    if not free.contains(pt):
        raise MapError(f"{p}: start ({pt.x}, {pt.y}) is not in free space (inside an obstacle or outside the boundary)")
    # Every ring bounds free space: an obstacle's holes too (a wall drawn as one polygon round
    # the rooms it encloses), or the sensor would see through those walls and the vehicle fly on.
    rings = [boundary.exterior, *boundary.interiors]
    for o in obstacles:
        rings.extend((o.exterior, *o.interiors))
    walls = np.vstack([_ring_segments(r) for r in rings])
    name = str(data.get("name") or p.stem)
    return World(name, boundary, tuple(obstacles), free, Pose2(pt.x, pt.y, math.radians(yaw_deg)), walls)
