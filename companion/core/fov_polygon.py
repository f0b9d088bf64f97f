"""Scan to field-of-view polygon (thesis 2.4): the free space one depth scan saw, in its own frame.

The sensor origin is the first vertex (for scans narrower than a full turn); the returns follow in
bearing order. Returns at max range (or with no return) are frontier vertices, others obstacle
vertices. An occlusion (a jump in range between neighbouring rays) inserts a frontier vertex so the
shadow behind the nearer object stays unknown instead of being claimed as free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.geometry import FloatArray, Pose2
from companion.core.messages import DepthScan


class VertexKind(IntEnum):
    """Type of a polygon vertex (thesis eq. 2.2 and 2.15)."""

    OBSTACLE = 0
    FRONTIER = 1
    FREE = 2


# The kinds as plain ints, for comparing with the int8 ``kinds`` arrays: numpy compares an
# IntEnum member about four times slower than an int (9 us against 2 us an array here, through
# the enum's attribute lookups), and the planner asks every keyframe it passes.
KIND_OBSTACLE, KIND_FRONTIER, KIND_FREE = int(VertexKind.OBSTACLE), int(VertexKind.FRONTIER), int(VertexKind.FREE)


class EdgeKind(IntEnum):
    """Type of the edge from vertex i to i+1 (thesis eq. 2.3, plus the FOV's side edges)."""

    OBSTACLE = 0
    FRONTIER = 1
    SIDE = 2  # an edge at the sensor origin: the FOV's side, beyond which nothing was seen


@dataclass(frozen=True, slots=True)
class PolygonParams:
    """Tuning for :func:`scan_to_polygon`."""

    occlusion_threshold_m: float = 0.5
    # A range jump between two returns on one straight surface (each within the tolerance of the
    # line its other neighbours draw) no farther apart than this is that surface seen at a grazing
    # angle, not an occlusion: no opening that wide can hide between them (0 disables).
    grazing_max_gap_m: float = 0.8
    grazing_line_tol_m: float = 0.06
    # An occlusion's shadow edge runs along the farther ray; frontier vertices along it at this
    # spacing keep the whole edge open until views cover each part, not just its near end.
    occlusion_frontier_spacing_m: float = 1.0
    min_vertex_spacing_m: float = 0.25
    frontier_range_tolerance_m: float = 0.02
    # The FOV's two side edges border space nothing has seen; frontier vertices placed along them
    # at this spacing let the planner look there too (0 disables them).
    side_frontier_spacing_m: float = 1.0


@dataclass(frozen=True, slots=True)
class FovPolygon:
    """One scan's free space in the keyframe frame.

    ``vertices_xy`` is (N, 2) in counter-clockwise order, ``kinds`` the initial ``VertexKind`` of
    each vertex, ``outward_xy`` a unit outward normal per vertex (used to ask whether the space just
    beyond a frontier was seen by another view), ``has_origin`` whether vertex 0 is the sensor.
    """

    vertices_xy: FloatArray
    kinds: NDArray[np.int8]
    outward_xy: FloatArray
    has_origin: bool
    shape: shapely.Polygon
    # Which vertices lie on an occlusion's shadow edge (the space beyond them is hidden behind an
    # occluder, often a door's jamb, not at the sensor's range or field-of-view limit).
    on_shadow: NDArray[np.bool_]
    # Which lie at the sensor's range limit (no return on their ray): not shadow, not invalid
    # returns (pinched to the minimum range), not the field of view's sides.
    at_range_limit: NDArray[np.bool_]

    @property
    def size(self) -> int:
        return int(self.vertices_xy.shape[0])

    def edge_kinds(self, kinds: NDArray[np.int8] | None = None) -> NDArray[np.int8]:
        """Edge i joins vertex i to i+1 (cyclic), typed from the vertex kinds given (or initial)."""
        k = self.kinds if kinds is None else kinds
        nxt = np.roll(k, -1)
        out = np.full(k.shape, EdgeKind.OBSTACLE, dtype=np.int8)
        out[(k == KIND_FRONTIER) | (nxt == KIND_FRONTIER)] = EdgeKind.FRONTIER
        if self.has_origin:
            out[0] = EdgeKind.SIDE if k[1] != KIND_FRONTIER else EdgeKind.FRONTIER
            out[-1] = EdgeKind.SIDE if k[-1] != KIND_FRONTIER else EdgeKind.FRONTIER
        return out

    def obstacle_segments(self) -> FloatArray:
        """(M, 2, 2) array of obstacle edges (both ends observed obstacle returns)."""
        return self._segments(self._obstacle_mask())

    def open_segments(self) -> FloatArray:
        """(M, 2, 2) array of the other edges: where the view's free space ends at space it did
        not see (its range limit, an occlusion's shadow, its field of view's sides)."""
        return self._segments(~self._obstacle_mask())

    def _obstacle_mask(self) -> NDArray[np.bool_]:
        k = self.kinds
        nxt = np.roll(k, -1)
        mask: NDArray[np.bool_] = (k == KIND_OBSTACLE) & (nxt == KIND_OBSTACLE)
        if self.has_origin:
            mask[0] = False
            mask[-1] = False
        return mask

    def _segments(self, mask: NDArray[np.bool_]) -> FloatArray:
        idx = np.flatnonzero(mask)
        nxt_idx = (idx + 1) % self.size
        return np.stack((self.vertices_xy[idx], self.vertices_xy[nxt_idx]), axis=1)


def _classify_ranges(scan: DepthScan, tol_m: float) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Effective ranges and frontier flags per ray, following the scan's range conventions."""
    r = scan.ranges_m
    with np.errstate(invalid="ignore"):
        no_return = np.isposinf(r) | (r >= scan.max_range_m - tol_m)
        too_close = np.isneginf(r)
        invalid = np.isnan(r) | (np.isfinite(r) & (r < scan.min_range_m))
    ranges = np.where(np.isfinite(r), r, 0.0)
    ranges = np.where(no_return, scan.max_range_m, ranges)
    # Too close: an obstacle right in front; invalid: nothing known along the ray. Either way the
    # polygon is pinched to the minimum range, never claiming free space that was not seen.
    ranges = np.where(too_close | invalid, max(scan.min_range_m, 1e-3), ranges)
    frontier = no_return | invalid
    return ranges.astype(np.float64), frontier


def _grazing(
    bearings: FloatArray,
    ranges: FloatArray,
    frontier: NDArray[np.bool_],
    jumps: NDArray[np.intp],
    max_gap_m: float,
    tol_m: float,
) -> NDArray[np.bool_]:
    """Which range jumps (between ray i and i+1) are one straight surface seen at a grazing
    angle: rays i and i+1 returned, at most ``max_gap_m`` apart, and each lies within ``tol_m``
    of the line through the other and the other's outer neighbour (i-1 or i+2). Range noise runs
    along the ray, nearly along such a surface, so the test across it is tight. A ray into an
    opening of the surface lands beyond the line or (in a thick wall) on the far jamb, as far
    along the line as the opening is wide: no opening wider than ``max_gap_m`` is taken for
    surface.

    Where one outer neighbour ran out of range (the surface leaves the sensor's range there),
    the other side draws the line from two returns: i on the line through i+2 and i+1, and i+1 on
    the line through i+3 and i+2 (or the mirror). Tested on both sides only, the last jump before
    the range limit along a wall seen this way stayed an occlusion: a frontier on the wall's face,
    flown to and seen as one again from each new spot (room seed 9: 30 s back and forth beside a
    pillar's face, 0.5 m off it, after coverage was full). One side alone, without i+3, was tried
    in session 13 and dropped (lshape 5 set a room's frontiers aside at coverage 0.980)."""
    out = np.zeros(jumps.size, dtype=bool)
    if max_gap_m <= 0.0 or jumps.size == 0:
        return out
    pts = np.column_stack((ranges * np.cos(bearings), ranges * np.sin(bearings)))
    n = ranges.size
    inner = (jumps >= 1) & (jumps + 2 < n)
    j = jumps[inner]
    if j.size == 0:
        return out
    returned = ~frontier
    a, b, c, d = pts[j - 1], pts[j], pts[j + 1], pts[j + 2]
    z, e = pts[np.maximum(j - 2, 0)], pts[np.minimum(j + 3, n - 1)]
    on_a_side = returned[j - 1] & (_off_line(a, b, c) <= tol_m)  # i+1 on the line of i-1, i
    on_d_side = returned[j + 2] & (_off_line(d, c, b) <= tol_m)  # i on the line of i+2, i+1
    a_straight = (j >= 2) & returned[np.maximum(j - 2, 0)] & (_off_line(z, a, b) <= tol_m)
    d_straight = (j + 3 < n) & returned[np.minimum(j + 3, n - 1)] & (_off_line(e, d, c) <= tol_m)
    both_sides = on_a_side & on_d_side
    a_side_only = on_a_side & a_straight & frontier[j + 2]
    d_side_only = on_d_side & d_straight & frontier[j - 1]
    close = np.hypot(*(c - b).T) <= max_gap_m
    ok = returned[j] & returned[j + 1] & close & (both_sides | a_side_only | d_side_only)
    out[np.flatnonzero(inner)] = ok
    return out


def _off_line(a: FloatArray, b: FloatArray, p: FloatArray) -> FloatArray:
    """Distance of each point ``p`` from the line through ``a`` and ``b`` (rows)."""
    ab = b - a
    cross = ab[:, 0] * (p - a)[:, 1] - ab[:, 1] * (p - a)[:, 0]
    return np.abs(cross) / np.maximum(np.hypot(ab[:, 0], ab[:, 1]), 1e-9)


def _insert_occlusions(
    bearings: FloatArray,
    ranges: FloatArray,
    frontier: NDArray[np.bool_],
    threshold_m: float,
    spacing_m: float,
    grazing_max_gap_m: float,
    grazing_tol_m: float,
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """Insert frontier vertices at each range jump (thesis eq. 2.4); the last array returned
    marks them (the shadow edges' vertices).

    The first sits at the nearer range on the farther ray, so the polygon edge from it runs along
    the farther ray (observed free) and the occluded wedge behind the nearer return stays outside.
    More follow along that edge every ``spacing_m``: a shadow edge metres long must not hinge on
    one vertex by the occluder, which the next view around the corner closes. A shorter edge gets
    one in its middle: the one by the occluder lies within a ray's width of the occluder's wall,
    where a view that saw the wall closes it (lshape 4 lost a room behind a door that way).
    """
    ranges = ranges.copy()
    frontier = frontier.copy()
    # A lone ray much longer than both neighbours would make a zero-width spike (out and back
    # along one bearing): cut it to the longer neighbour, as unknown beyond.
    if ranges.size >= 3:
        longer = np.maximum(ranges[:-2], ranges[2:])
        spike = np.flatnonzero(ranges[1:-1] - longer > threshold_m) + 1
        ranges[spike] = longer[spike - 1]
        frontier[spike] = True
    # A jump at either end ray would leave a zero-width spike along that ray (the polygon returns
    # to the origin along it): cut the end ray back to its neighbour's range, as unknown.
    for end, inner in ((0, 1), (-1, -2)):
        if ranges[end] - ranges[inner] > threshold_m:
            ranges[end] = ranges[inner]
            frontier[end] = True
    jumps = np.flatnonzero(np.abs(np.diff(ranges)) > threshold_m)
    jumps = jumps[~_grazing(bearings, ranges, frontier, jumps, grazing_max_gap_m, grazing_tol_m)]
    if jumps.size == 0:
        return bearings, ranges, frontier, np.zeros(bearings.size, dtype=bool)
    b_out: list[float] = []
    r_out: list[float] = []
    f_out: list[bool] = []
    s_out: list[bool] = []
    jump_set = set(jumps.tolist())
    for i in range(bearings.size):
        b_out.append(float(bearings[i]))
        r_out.append(float(ranges[i]))
        f_out.append(bool(frontier[i]))
        s_out.append(False)
        if i in jump_set:
            near, far = min(ranges[i], ranges[i + 1]), max(ranges[i], ranges[i + 1])
            rising = ranges[i] < ranges[i + 1]
            far_bearing = bearings[i + 1] if rising else bearings[i]
            along = [near]
            if spacing_m > 0.0:
                inner = np.arange(near + spacing_m, far - 0.5 * spacing_m, spacing_m).tolist()
                along += inner or [0.5 * (near + far)]
            for r in along if rising else along[::-1]:
                b_out.append(float(far_bearing))
                r_out.append(float(r))
                f_out.append(True)
                s_out.append(True)
    return np.array(b_out), np.array(r_out), np.array(f_out, dtype=bool), np.array(s_out, dtype=bool)


def _subsample(points: FloatArray, frontier: NDArray[np.bool_], spacing_m: float) -> NDArray[np.intp]:
    """Indices to keep: drop a vertex closer than ``spacing_m`` to the last kept one of the same
    kind, but always keep the ends and both sides of every kind change."""
    n = points.shape[0]
    change = np.zeros(n, dtype=bool)
    change[1:] |= frontier[1:] != frontier[:-1]
    change[:-1] |= frontier[:-1] != frontier[1:]
    change[0] = change[-1] = True
    keep = [0]
    last = points[0]
    for i in range(1, n):
        if change[i] or math.hypot(points[i, 0] - last[0], points[i, 1] - last[1]) >= spacing_m:
            keep.append(i)
            last = points[i]
    return np.asarray(keep, dtype=np.intp)


def _outward_normals(vertices: FloatArray) -> FloatArray:
    """Unit outward normal per vertex of a counter-clockwise ring (mean of its edges' normals)."""
    nxt = np.roll(vertices, -1, axis=0)
    edge = nxt - vertices
    # Outward normal of a CCW edge (dx, dy) is (dy, -dx).
    en = np.column_stack((edge[:, 1], -edge[:, 0]))
    en /= np.maximum(np.linalg.norm(en, axis=1, keepdims=True), 1e-12)
    vn = en + np.roll(en, 1, axis=0)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    # A cusp (antiparallel edges) has no mean; fall back to the outgoing edge's normal.
    return np.where(norm > 1e-6, vn / np.maximum(norm, 1e-12), en)


def scan_to_polygon(scan: DepthScan, params: PolygonParams | None = None) -> FovPolygon:
    """Build the field-of-view polygon of ``scan`` in its own (body = keyframe) frame."""
    p = params or PolygonParams()
    ranges, frontier = _classify_ranges(scan, p.frontier_range_tolerance_m)
    bearings, ranges, frontier, shadow = _insert_occlusions(
        scan.bearings_rad,
        ranges,
        frontier,
        p.occlusion_threshold_m,
        p.occlusion_frontier_spacing_m,
        p.grazing_max_gap_m,
        p.grazing_line_tol_m,
    )
    pts = np.column_stack((ranges * np.cos(bearings), ranges * np.sin(bearings)))
    keep = _subsample(pts, frontier, p.min_vertex_spacing_m)
    pts, frontier, shadow = pts[keep], frontier[keep], shadow[keep]
    limit = frontier & ~shadow & (ranges[keep] >= scan.max_range_m)  # no return: set to the maximum
    span = scan.bearings_rad[-1] - scan.bearings_rad[0]
    increment = span / (scan.bearings_rad.size - 1)
    has_origin = span + 1.5 * increment < 2.0 * math.pi
    kinds = np.where(frontier, VertexKind.FRONTIER, VertexKind.OBSTACLE).astype(np.int8)
    if has_origin:
        first = _side_points(pts[0], p.side_frontier_spacing_m)
        last = _side_points(pts[-1], p.side_frontier_spacing_m)[::-1]
        pts = np.vstack((np.zeros((1, 2)), first, pts, last))
        shadow = np.concatenate((np.zeros(1 + first.shape[0], dtype=bool), shadow, np.zeros(last.shape[0], dtype=bool)))
        limit = np.concatenate((np.zeros(1 + first.shape[0], dtype=bool), limit, np.zeros(last.shape[0], dtype=bool)))
        kinds = np.concatenate(
            (
                np.array([VertexKind.FREE], dtype=np.int8),
                np.full(first.shape[0], VertexKind.FRONTIER, dtype=np.int8),
                kinds,
                np.full(last.shape[0], VertexKind.FRONTIER, dtype=np.int8),
            )
        )
    if pts.shape[0] < 3:  # a sensor reaching less than a vertex spacing, seen by a ray or two: no area
        none = np.zeros(0, dtype=bool)
        return FovPolygon(
            np.zeros((0, 2)), np.zeros(0, dtype=np.int8), np.zeros((0, 2)), False, shapely.Polygon(), none, none
        )
    shape = shapely.Polygon(pts)
    if not shape.is_valid:
        shape = _largest_valid_part(shape)
    shapely.prepare(shape)
    return FovPolygon(pts, kinds, _outward_normals(pts), has_origin, shape, shadow, limit)


def _side_points(end_xy: FloatArray, spacing_m: float) -> FloatArray:
    """Points from the origin towards ``end_xy`` every ``spacing_m``, stopping short of it."""
    length = float(np.hypot(end_xy[0], end_xy[1]))
    if spacing_m <= 0.0 or length < 1.5 * spacing_m:
        return np.zeros((0, 2))
    steps = np.arange(spacing_m, length - 0.5 * spacing_m, spacing_m)
    return np.outer(steps / length, end_xy)


def _largest_valid_part(shape: shapely.Polygon) -> shapely.Polygon:
    """Repair a self-touching ring (possible with coincident returns) to its largest polygon."""
    fixed = shapely.make_valid(shape)
    polys = [g for g in getattr(fixed, "geoms", [fixed]) if isinstance(g, shapely.Polygon)]
    if not polys:
        return shapely.Polygon()
    return max(polys, key=lambda g: g.area)


def has_return(scan: DepthScan, no_return_margin_m: float) -> NDArray[np.bool_]:
    """Which rays hit something: a finite range from the minimum up to ``no_return_margin_m``
    short of the maximum (REP 117; a range at the limit is read as no return, as the polygon does)."""
    r = scan.ranges_m
    with np.errstate(invalid="ignore"):
        hit: NDArray[np.bool_] = np.isfinite(r) & (r >= scan.min_range_m) & (r < scan.max_range_m - no_return_margin_m)
    return hit


def returns_xy(scan: DepthScan, no_return_margin_m: float) -> FloatArray:
    """The scan's obstacle returns (see :func:`has_return`) as body-frame points."""
    ok = has_return(scan, no_return_margin_m)
    r, b = scan.ranges_m[ok], scan.bearings_rad[ok]
    return np.column_stack((r * np.cos(b), r * np.sin(b)))


def _nearest_rays(
    scan: DepthScan, sensor: Pose2, points_xy: FloatArray
) -> tuple[FloatArray, NDArray[np.intp], NDArray[np.bool_], FloatArray]:
    """Each point's range from the sensor, the ray nearest its bearing, whether that ray passes
    through it (the bearing within half a ray's spacing, so not outside the field of view), and
    the bearing itself."""
    pts = sensor.inverse().apply(np.asarray(points_xy, dtype=np.float64).reshape(-1, 2))
    rng = np.hypot(pts[:, 0], pts[:, 1])
    bearing = np.arctan2(pts[:, 1], pts[:, 0])
    b = scan.bearings_rad
    j = np.minimum(np.maximum(np.searchsorted(b, bearing), 1), b.size - 1)
    j = np.where(np.abs(bearing - b[j - 1]) <= np.abs(bearing - b[j]), j - 1, j)
    on_ray = np.abs(bearing - b[j]) <= 0.5 * np.abs(_spacing_at(b, j))
    return rng, j, on_ray, bearing


def _spacing_at(bearings_rad: FloatArray, j: NDArray[np.intp]) -> FloatArray:
    """``np.gradient(bearings_rad)[j]`` (the same arithmetic, so the same bits) for just the rays
    asked about: the whole gradient, every scan, cost more than the rest of the lookup. A
    :class:`DepthScan` has two rays at least."""
    n = bearings_rad.size
    inner = (bearings_rad[np.minimum(j + 1, n - 1)] - bearings_rad[np.maximum(j - 1, 0)]) / 2.0
    first = bearings_rad[1] - bearings_rad[0]
    last = bearings_rad[n - 1] - bearings_rad[n - 2]
    return np.where(j == 0, first, np.where(j == n - 1, last, inner))


def _past_return_m(
    scan: DepthScan, sensor: Pose2, points_xy: FloatArray, no_return_margin_m: float
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """How far each point lies past the return of the ray through it (negative: in front of it),
    and whether there is such a ray that returned (:func:`has_return`; inside the field of view)."""
    rng, j, on_ray, _ = _nearest_rays(scan, sensor, points_xy)
    returned: NDArray[np.bool_] = on_ray & has_return(scan, no_return_margin_m)[j]
    past: FloatArray = rng - scan.ranges_m[j]
    return past, returned


def on_scanned_surface(
    scan: DepthScan, sensor: Pose2, points_xy: FloatArray, tol_m: float, no_return_margin_m: float
) -> NDArray[np.bool_]:
    """Which points (in the frame ``sensor`` is given in) the scan sees as surface: the ray
    through the point returned (:func:`has_return`) within ``tol_m`` of the point's range. A
    point nearer than the return is seen free, one farther is hidden behind it; neither is
    surface. Points outside the field of view, or along rays without a return, are not."""
    past, returned = _past_return_m(scan, sensor, points_xy, no_return_margin_m)
    with np.errstate(invalid="ignore"):
        surface: NDArray[np.bool_] = returned & (np.abs(past) <= tol_m)
    return surface


def behind_scanned_surface(
    scan: DepthScan, sensor: Pose2, points_xy: FloatArray, depth_m: float, no_return_margin_m: float
) -> NDArray[np.bool_]:
    """Which points the scan sees hidden behind a surface: the ray through the point returned
    (:func:`has_return`) more than ``depth_m`` short of it."""
    past, returned = _past_return_m(scan, sensor, points_xy, no_return_margin_m)
    with np.errstate(invalid="ignore"):
        hidden: NDArray[np.bool_] = returned & (past > depth_m)
    return hidden


def seen_past(
    scan: DepthScan,
    sensor: Pose2,
    points_xy: FloatArray,
    depth_m: float,
    fov_margin_rad: float = 0.0,
    nearest_m: float = 0.0,
) -> NDArray[np.bool_]:
    """Which points the scan sees at least ``depth_m`` past, along the ray through each: the ray
    ran on that far (to a return, or to the maximum range with none), the point at least
    ``fov_margin_rad`` inside the field of view and farther than ``nearest_m`` from the sensor.
    Invalid (NaN) readings see nothing."""
    rng, j, on_ray, bearing = _nearest_rays(scan, sensor, points_xy)
    b = scan.bearings_rad
    r = scan.ranges_m[j]
    ran_m = np.where(np.isnan(r), 0.0, np.minimum(r, scan.max_range_m))  # +inf: no return in range
    ok = on_ray & (bearing >= b[0] + fov_margin_rad) & (bearing <= b[-1] - fov_margin_rad) & (rng > nearest_m)
    seen: NDArray[np.bool_] = ok & (rng + depth_m <= scan.max_range_m) & (ran_m >= rng + depth_m)
    return seen


def in_view(scan: DepthScan, sensor: Pose2, points_xy: FloatArray, margin_m: float = 0.0) -> NDArray[np.bool_]:
    """Which points the scan has its own say about: inside the field of view, on a ray with a
    valid reading, at or beyond the minimum range (and within the maximum range where the ray
    returned nothing). Such a point is seen through, seen as the surface the ray returned from,
    or hidden behind it; a remembered return there is superseded by the scan. Points nearer than
    the minimum range, or on rays with an invalid (NaN) reading, the scan cannot see. Nor, with
    a ``margin_m`` (how well a remembered point is known), one its ray sees through (returns
    more than that beyond it) but that lies within that margin of the field of view's edge: the
    wall's end it was seen on may lie just outside, where no ray passes."""
    rng, j, on_ray, bearing = _nearest_rays(scan, sensor, points_xy)
    r = scan.ranges_m[j]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(r) & (r >= scan.min_range_m) | np.isposinf(r)
        out_of_range = (rng > scan.max_range_m) & ~(r < scan.max_range_m)
    seen: NDArray[np.bool_] = on_ray & valid & (rng >= scan.min_range_m) & ~out_of_range
    if margin_m > 0.0 and seen.any():
        spread = np.arcsin(np.clip(margin_m / np.maximum(rng, 1e-9), 0.0, 1.0))
        b = scan.bearings_rad  # ascending, as _nearest_rays takes them
        inside = (bearing - spread >= b[0]) & (bearing + spread <= b[-1])
        seen &= inside | ~(r - rng > margin_m)  # by the edge: superseded only by a return at or before it
    return seen
