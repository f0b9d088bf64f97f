import math

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.core.errors import ScanError
from companion.core.explorer import Explorer
from companion.core.fov_polygon import (
    PolygonParams,
    VertexKind,
    behind_scanned_surface,
    in_view,
    on_scanned_surface,
    scan_to_polygon,
    seen_past,
)
from companion.core.geometry import Pose2
from companion.core.messages import DepthScan, Odometry
from sitl.depth_sensor import cast_rays

BEARINGS = np.linspace(-math.pi / 4, math.pi / 4, 64)


def polar(bearing: float, range_m: float) -> list[float]:
    """The point at that bearing and range from the sensor."""
    return [range_m * math.cos(bearing), range_m * math.sin(bearing)]


def scan(ranges, bearings=BEARINGS, max_range=5.0):
    return DepthScan(0.0, bearings, np.asarray(ranges, dtype=float), max_range)


def test_only_rays_without_a_return_are_at_the_range_limit():
    """No return (``inf`` or the maximum) is the range limit; an invalid return (NaN, pinched to
    the minimum range) is a frontier too but not there, nor are the sides' frontier vertices or
    the hits."""
    r = np.full(64, 3.0)
    r[:20] = np.inf
    r[20:28] = 5.0
    r[40:48] = np.nan
    poly = scan_to_polygon(scan(r))
    norm = np.linalg.norm(poly.vertices_xy, axis=1)
    limit = poly.at_range_limit
    assert limit.any() and np.allclose(norm[limit], 5.0)
    frontier = poly.kinds == VertexKind.FRONTIER
    assert np.all(frontier[limit])
    assert np.any(frontier & (norm < 1.0)) and not np.any(limit & (norm < 1.0))  # the invalid rays
    assert np.any(frontier & ~limit & (norm > 1.0))  # the sides' vertices
    assert not np.any(limit & (poly.kinds == VertexKind.OBSTACLE))


def test_open_space_gives_frontier_arc_and_origin_first():
    poly = scan_to_polygon(scan(np.full(64, 5.0)))
    assert poly.has_origin and np.allclose(poly.vertices_xy[0], 0.0)
    arc = np.linalg.norm(poly.vertices_xy, axis=1) > 4.9
    assert arc.any() and np.all(poly.kinds[arc] == VertexKind.FRONTIER)
    assert poly.obstacle_segments().shape[0] == 0


def test_wall_returns_are_obstacle_vertices():
    poly = scan_to_polygon(scan(np.full(64, 2.0)))
    ranges = np.linalg.norm(poly.vertices_xy, axis=1)
    on_wall = np.isclose(ranges, 2.0)
    assert on_wall.sum() >= 2 and np.all(poly.kinds[on_wall] == VertexKind.OBSTACLE)
    assert poly.obstacle_segments().shape[0] >= 1


def test_occlusion_inserts_frontier_on_the_far_ray_at_the_near_range():
    r = np.full(64, 4.0)
    r[30:] = 1.5  # a near object covering the left half
    poly = scan_to_polygon(scan(r), PolygonParams(min_vertex_spacing_m=0.0, side_frontier_spacing_m=0.0))
    inserted = [
        i
        for i, v in enumerate(poly.vertices_xy)
        if poly.kinds[i] == VertexKind.FRONTIER and np.isclose(np.hypot(*v), 1.5)
    ]
    assert len(inserted) == 1
    # The shadow behind the near object (far range on the near ray) is not claimed as free.
    shadow = 3.0 * np.array([math.cos(BEARINGS[30]), math.sin(BEARINGS[30])])
    assert not poly.shape.contains(shapely.Point(shadow))


@pytest.mark.parametrize("near_first", [True, False])
def test_a_long_shadow_edge_carries_frontier_vertices_along_its_length(near_first):
    """Each part of a shadow edge must stay open on its own: the vertex by the occluder is the
    first a view round the corner closes, while the far part may still be unseen."""
    r = np.full(64, 4.6)
    if near_first:
        r[:30] = 0.8  # near object on the right: the range rises across the jump
    else:
        r[30:] = 0.8  # near object on the left: the range falls across the jump
    params = PolygonParams(occlusion_frontier_spacing_m=1.0, side_frontier_spacing_m=0.0)
    poly = scan_to_polygon(scan(r), params)
    far_ray = BEARINGS[30] if near_first else BEARINGS[29]
    on_edge = [
        float(np.hypot(*v))
        for v, k in zip(poly.vertices_xy, poly.kinds, strict=True)
        if k == VertexKind.FRONTIER and np.isclose(math.atan2(v[1], v[0]), far_ray) and np.hypot(*v) < 4.5
    ]
    assert sorted(on_edge) == pytest.approx([0.8, 1.8, 2.8, 3.8])
    # Those, and only those, are marked as on a shadow edge (not the range limit's, nor the sides').
    marked = poly.vertices_xy[poly.on_shadow]
    assert sorted(np.hypot(*marked.T)) == pytest.approx([0.8, 1.8, 2.8, 3.8])
    # They lie on the edge: the free space is the same as with the single vertex.
    single = scan_to_polygon(scan(r), PolygonParams(occlusion_frontier_spacing_m=0.0, side_frontier_spacing_m=0.0))
    assert poly.shape.is_valid and math.isclose(poly.shape.area, single.shape.area, rel_tol=1e-6)


def test_a_short_shadow_edge_gets_a_frontier_vertex_in_its_middle_off_the_occluder():
    """lshape 4: a door jamb 3 m away, the room's far wall 1.1 m behind it. The vertex by the jamb
    lies within a ray's width of the jamb's wall (a view that saw that wall closes it); the one in
    the middle of the shadow edge keeps the room behind the door open."""
    r = np.full(64, 4.1)
    r[:30] = 3.0  # the jamb on the right; through the door to the far wall on the left
    poly = scan_to_polygon(scan(r), PolygonParams(occlusion_frontier_spacing_m=1.0, side_frontier_spacing_m=0.0))
    on_edge = [
        float(np.hypot(*v))
        for v, k in zip(poly.vertices_xy, poly.kinds, strict=True)
        if k == VertexKind.FRONTIER and np.isclose(math.atan2(v[1], v[0]), BEARINGS[30])
    ]
    assert sorted(on_edge) == pytest.approx([3.0, 3.55])


def _grazing_wall_scan(door: tuple[float, float] | None) -> DepthScan:
    """A 0.2 m thick wall along y = 0.4 on the left, seen from the origin looking along x (rays
    land 0.5-0.8 m apart on it 2.5-3.5 m out), with an optional door in it and a room behind."""
    x0, x1 = door or (30.0, 30.0)
    walls = [((-1.0, 0.4), (x0, 0.4)), ((x1, 0.4), (30.0, 0.4)), ((-1.0, 3.0), (30.0, 3.0))]
    if door is not None:
        walls += [((x0, 0.4), (x0, 0.6)), ((x1, 0.4), (x1, 0.6)), ((-1.0, 0.6), (x0, 0.6)), ((x1, 0.6), (30.0, 0.6))]
    r = cast_rays(np.zeros(2), BEARINGS, np.array(walls, dtype=float), 5.0)
    return scan(np.where(np.isfinite(r), r, 5.0))


def _shadow_vertices(poly, x_range: tuple[float, float]) -> np.ndarray:
    """Frontier vertices short of the range limit on the left (y > 0.1) within ``x_range``."""
    v = poly.vertices_xy
    pick = (poly.kinds == VertexKind.FRONTIER) & (np.hypot(v[:, 0], v[:, 1]) < 4.9) & (v[:, 1] > 0.1)
    pick &= (v[:, 0] >= x_range[0]) & (v[:, 0] <= x_range[1])
    return v[pick]


def test_a_wall_seen_at_a_grazing_angle_is_one_surface_not_occlusions():
    """Rays landing far apart along one straight wall jump in range, but nothing is hidden
    between them: no frontier vertex along the wall (a flight to one finds only the wall)."""
    wall = _grazing_wall_scan(None)
    # Up to x = 3.4 m; farther on, the wall runs out of the sensor's range: unknown, rightly.
    assert _shadow_vertices(scan_to_polygon(wall), (0.0, 3.4)).shape[0] == 0
    as_occlusions = scan_to_polygon(wall, PolygonParams(grazing_max_gap_m=0.0))
    assert _shadow_vertices(as_occlusions, (0.0, 3.4)).shape[0] > 0


def test_a_door_in_a_wall_seen_at_a_grazing_angle_stays_an_occlusion():
    """The ray into a 1 m door lands on the far jamb, within the wall's thickness of its line
    but a door's width along it: the room behind stays unknown, behind a frontier."""
    poly = scan_to_polygon(_grazing_wall_scan((2.4, 3.4)))
    assert _shadow_vertices(poly, (2.0, 3.4)).shape[0] > 0


def _wall_leaving_the_range_scan(door_x0: float | None) -> DepthScan:
    """A 0.15 m thick wall along y = 0.45 on the left, seen from the origin looking along x: its
    returns jump 0.5-0.8 m apart as it leaves the 5 m range past x = 4 m (the last ray before the
    limit lands at x = 3.99, the one before at 3.26); with an optional 1 m door from ``door_x0``."""
    y, t = 0.45, 0.15
    if door_x0 is None:
        walls = [((-1.0, y), (30.0, y))]
    else:
        x1 = door_x0 + 1.0
        walls = [((-1.0, y), (door_x0, y)), ((x1, y), (30.0, y)), ((door_x0, y), (door_x0, y + t))]
        walls += [((x1, y), (x1, y + t)), ((-1.0, y + t), (door_x0, y + t)), ((x1, y + t), (30.0, y + t))]
    r = cast_rays(np.zeros(2), BEARINGS, np.array([*walls, ((-1.0, 3.0), (30.0, 3.0))], dtype=float), 5.0)
    return scan(np.where(np.isfinite(r), r, 5.0))


def _shadow_xs(poly) -> list[float]:
    """The x of every shadow-edge frontier vertex on the left (y > 0.1)."""
    v = poly.vertices_xy
    pick = poly.on_shadow & (poly.kinds == VertexKind.FRONTIER) & (v[:, 1] > 0.1)
    return sorted(v[pick, 0].round(2).tolist())


def test_a_grazing_wall_is_one_surface_up_to_its_last_return_before_the_range_limit():
    """The jump between the wall's last two returns has no return beyond it to draw the line
    from on that side; the two returns before it on the other side draw it: no frontier on the
    wall's face (one there is flown to and seen as one again from each spot). Beyond the last
    return, where the wall leaves the range, the space stays unknown."""
    xs = _shadow_xs(scan_to_polygon(_wall_leaving_the_range_scan(None)))
    assert xs and all(x >= 3.95 for x in xs)  # only along the ray past the last return
    as_occlusions = _shadow_xs(
        scan_to_polygon(_wall_leaving_the_range_scan(None), PolygonParams(grazing_max_gap_m=0.0))
    )
    assert any(3.2 < x < 3.95 for x in as_occlusions)


@pytest.mark.parametrize("door_x0", [3.3, 3.5, 3.7, 3.9])
def test_a_door_by_the_range_limit_in_a_grazing_wall_stays_an_occlusion(door_x0):
    """The last ray before the range limit passes into a 1 m door and lands on its far jamb:
    off the wall's line by up to its thickness, so the room behind stays behind a frontier."""
    xs = _shadow_xs(scan_to_polygon(_wall_leaving_the_range_scan(door_x0)))
    assert any(3.2 < x < door_x0 + 1.0 for x in xs)


def test_invalid_returns_never_become_walls_at_zero():
    r = np.full(64, 3.0)
    r[10] = np.nan
    r[11] = -1.0
    r[12:20] = np.inf
    poly = scan_to_polygon(scan(r), PolygonParams(min_vertex_spacing_m=0.0, side_frontier_spacing_m=0.0))
    ranges = np.linalg.norm(poly.vertices_xy[1:], axis=1)
    assert ranges.min() >= 0.1 - 1e-9
    # no-return ray becomes a frontier at max range
    assert np.any(np.isclose(ranges, 5.0) & (poly.kinds[1:] == VertexKind.FRONTIER))


def test_subsampling_keeps_fewer_vertices_but_all_kind_changes():
    r = np.full(64, 5.0)
    r[20:40] = 2.0
    dense = scan_to_polygon(scan(r), PolygonParams(min_vertex_spacing_m=0.0))
    sparse = scan_to_polygon(scan(r), PolygonParams(min_vertex_spacing_m=0.5))
    assert sparse.size < dense.size
    assert np.count_nonzero(np.diff(sparse.kinds[1:]) != 0) == np.count_nonzero(np.diff(dense.kinds[1:]) != 0)


@pytest.mark.parametrize(
    "bearings",
    [np.array([0.0]), np.array([0.0, 0.0, 0.1]), np.linspace(0, 7, 10), np.array([0.0, np.nan])],
)
def test_malformed_bearings_are_rejected(bearings):
    with pytest.raises(ScanError):
        DepthScan(0.0, bearings, np.ones_like(bearings), 5.0)


def test_full_turn_scan_has_no_origin_vertex():
    b = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    poly = scan_to_polygon(DepthScan(0.0, b, np.full(360, 3.0), 5.0))
    assert not poly.has_origin
    assert poly.shape.contains(shapely.Point(0.0, 0.0))


ranges_st = st.lists(
    st.one_of(st.floats(0.0, 6.0), st.just(float("nan")), st.just(float("inf")), st.just(-1.0)),
    min_size=8,
    max_size=80,
)


@settings(max_examples=150, deadline=None)
@given(ranges_st, st.floats(0.3, 3.1))
def test_random_scans_give_valid_polygons_that_hold_their_origin(ranges, fov):
    b = np.linspace(-fov / 2, fov / 2, len(ranges))
    poly = scan_to_polygon(DepthScan(0.0, b, np.array(ranges), 5.0))
    assert poly.shape.is_valid
    assert poly.shape.covers(shapely.Point(0.0, 0.0))
    assert poly.kinds.shape[0] == poly.vertices_xy.shape[0]
    assert np.all(np.linalg.norm(poly.vertices_xy, axis=1) <= 5.0 + 1e-9)


def test_on_scanned_surface_is_where_the_ray_through_a_point_returned_at_its_range():
    r = np.full(64, 3.0)
    r[40:] = 5.0  # no return on the left part
    s = scan(r)
    sensor = Pose2(1.0, 2.0, 0.5)  # the points below are given in the frame the sensor pose is in
    body = np.array(
        [
            [3.0, 0.0],  # on the wall the scan sees
            [2.0, 0.0],  # in front of it: seen free
            [4.0, 0.0],  # behind it: hidden, not known to be surface
            [5.0 * math.cos(0.5), 5.0 * math.sin(0.5)],  # at the range limit of a ray without a return
            [0.0, 3.0],  # outside the field of view
        ]
    )
    pts = sensor.apply(body)
    assert on_scanned_surface(s, sensor, pts, 0.15, 0.02).tolist() == [True, False, False, False, False]
    # Hidden behind the surface by more than 0.3 m: only the point 1 m behind the wall.
    assert behind_scanned_surface(s, sensor, pts, 0.3, 0.02).tolist() == [False, False, True, False, False]
    assert not behind_scanned_surface(s, sensor, sensor.apply(np.array([[3.2, 0.0]])), 0.3, 0.02)[0]


def test_an_occlusion_frontier_is_not_taken_for_surface():
    """The vertex put at the near range on the far ray lies next to the occluder's return, yet
    the ray through it returned far away: the shadow behind stays a frontier."""
    r = np.full(64, 4.0)
    r[30:] = 1.5
    poly = scan_to_polygon(scan(r), PolygonParams(min_vertex_spacing_m=0.0, side_frontier_spacing_m=0.0))
    frontier = poly.vertices_xy[poly.kinds == VertexKind.FRONTIER]
    occlusion = frontier[np.isclose(np.linalg.norm(frontier, axis=1), 1.5, atol=0.05)]
    assert occlusion.shape[0] >= 1
    assert not on_scanned_surface(scan(r), Pose2(0.0, 0.0, 0.0), occlusion, 0.15, 0.02).any()


def test_in_view_is_what_the_scan_has_its_own_say_about():
    """A point the scan sees through, sees as its surface or hides behind a return is in view
    (a remembered return there is superseded); one outside the field of view, nearer than the
    minimum range, on a ray with an invalid reading, or past the maximum range where the ray
    returned nothing, the scan cannot see."""
    bearings = np.linspace(-math.pi / 4, math.pi / 4, 64)
    ranges = np.full(64, 2.0)  # a wall 2 m along every ray ...
    ranges[bearings > 0.5] = 5.0  # ... but no return on the left-most rays (5 m: the maximum)
    ranges[np.abs(bearings) < 0.02] = np.nan  # and an invalid reading straight ahead
    scan = DepthScan(0.0, bearings, ranges, 5.0, min_range_m=0.3)

    points = np.array(
        [
            polar(-0.3, 1.0),  # seen through
            polar(-0.3, 2.0),  # the surface
            polar(-0.3, 3.0),  # hidden behind it
            polar(0.7, 4.0),  # seen through, no return
            polar(0.7, 6.0),  # past the maximum range, no return: not seen
            polar(-0.3, 0.2),  # nearer than the minimum range
            polar(0.0, 1.0),  # on the invalid ray
            polar(1.2, 1.0),  # outside the field of view
        ]
    )
    sensor = Pose2(1.0, -2.0, 0.4)  # the same, placed in another frame
    got = in_view(scan, sensor, sensor.apply(points))
    assert got.tolist() == [True, True, True, True, False, False, False, False]


def test_a_remembered_return_by_the_field_of_views_edge_is_not_superseded_within_the_margin():
    """A wall's end just outside the field of view, remembered a few centimetres off (drift),
    can lie just inside it, where the edge rays pass the real end and see through the
    remembered one. Seen through within ``margin_m`` of the edge, the scan does not have its
    say: forgotten there, the vehicle turned round the wall's end into it (apartment seed 4, in
    a variant)."""
    scan = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0, min_range_m=0.1)  # nothing in view

    edge = math.pi / 4
    points = np.array(
        [
            polar(-edge + math.radians(1.0), 0.55),  # 1 degree inside the edge, 0.55 m away: 1 cm in
            polar(edge - math.radians(1.0), 0.55),  # the same by the other edge
            polar(-edge + math.radians(1.0), 4.0),  # 1 degree inside, 4 m away: 7 cm in
            polar(-edge + math.radians(15.0), 0.55),  # well inside: 14 cm in
            polar(0.0, 2.0),  # the middle
        ]
    )
    assert in_view(scan, Pose2.identity(), points).tolist() == [True] * 5  # no margin: all superseded
    got = in_view(scan, Pose2.identity(), points, margin_m=0.1)
    assert got.tolist() == [False, False, False, True, True]
    # Where the ray by the edge returns at the point (or before it), the scan's own return
    # stands in for it: superseded, margin or not.
    walled = DepthScan(0.0, BEARINGS, np.full(64, 0.55), 5.0, min_range_m=0.1)
    assert in_view(walled, Pose2.identity(), points[:2], margin_m=0.1).tolist() == [True, True]


def test_a_point_is_seen_past_only_where_its_ray_runs_on_that_far_inside_the_field_of_view():
    """A wall 3 m ahead on the right part, no return on the left part (the ray runs to 5 m), one
    invalid reading: a point 1 m or more short of where its ray ends is seen past; one nearer the
    wall than that, one by the field of view's edge, one beside the sensor, or one on the
    invalid ray, is not."""
    r = np.full(64, 3.0)
    r[40:] = np.inf  # no return: the ray runs to the maximum range
    r[20] = np.nan
    s = scan(r)
    sensor = Pose2(1.0, 2.0, 0.5)  # the points below are given in the frame the sensor pose is in
    b = s.bearings_rad
    body = np.array(
        [
            [1.5, 0.0],  # 1.5 m in front of the wall: seen past
            [2.5, 0.0],  # 0.5 m in front of it: not 1 m
            [3.5 * math.cos(b[50]), 3.5 * math.sin(b[50])],  # 1.5 m short of the range limit
            [4.5 * math.cos(b[50]), 4.5 * math.sin(b[50])],  # 0.5 m short of it
            [1.0 * math.cos(b[62]), 1.0 * math.sin(b[62])],  # within 0.1 rad of the edge
            [0.2, 0.0],  # beside the sensor
            [1.0 * math.cos(b[20]), 1.0 * math.sin(b[20])],  # on the invalid ray
        ]
    )
    got = seen_past(s, sensor, sensor.apply(body), 1.0, fov_margin_rad=0.1, nearest_m=0.3)
    assert got.tolist() == [True, False, True, False, False, False, False]


def test_a_scan_capped_to_a_shorter_range_reads_farther_returns_as_none():
    """``DepthScan.capped``: returns at or beyond the cap become no return (+inf) at the cap's
    range, nearer ones, invalid (NaN) and too-near (-inf) readings stay; a scan already within the
    cap is itself; one whose minimum range is past the cap sees nothing the map takes: refused."""
    b = np.linspace(-0.5, 0.5, 6)
    scan = DepthScan(1.0, b, np.array([3.0, 25.0, np.nan, -np.inf, 20.0, np.inf]), 655.0, 0.2)
    capped = scan.capped(20.0)
    assert capped.max_range_m == 20.0 and capped.min_range_m == 0.2 and capped.stamp_s == 1.0
    np.testing.assert_array_equal(capped.ranges_m, [3.0, np.inf, np.nan, -np.inf, np.inf, np.inf])
    assert scan.capped(1000.0) is scan
    polygon = scan_to_polygon(capped)
    assert float(np.max(np.hypot(*polygon.vertices_xy.T))) <= 20.0 + 1e-9
    with pytest.raises(ScanError, match="minimum range"):
        DepthScan(1.0, b, np.full(6, 30.0), 655.0, 25.0).capped(20.0)


def test_a_scan_too_short_to_span_an_area_is_an_empty_view_not_an_error():
    """Two rays of a 0.1 m sensor leave fewer than three vertices after the vertex spacing:
    shapely raised a ValueError (uncaught by the service, which stops on the core's own errors).
    Now an empty view, which the explorer does not keep as a keyframe."""
    scan = DepthScan(0.0, np.array([-1.7, 1.7]), np.array([0.05, 0.08]), 0.1, 0.01)
    polygon = scan_to_polygon(scan)
    assert polygon.shape.is_empty and polygon.vertices_xy.shape == (0, 2) and polygon.kinds.size == 0
    ex = Explorer()
    result = ex.step(Odometry(0.0, Pose2()), scan)
    assert not result.keyframe_added and len(ex.map) == 0
