import math

import numpy as np
import pytest
import shapely
from hypothesis import given
from hypothesis import strategies as st

from companion.core.geometry import (
    Pose2,
    apply_grouped,
    closest_on_segments,
    first_contact,
    point_segment_distances,
    wrap_angle,
)
from companion.core.scan_matching import _WallTable

coord = st.floats(-100, 100, allow_nan=False)
angle = st.floats(-10, 10, allow_nan=False)
poses = st.builds(Pose2, coord, coord, angle)


def test_wrap_angle_maps_into_half_open_interval():
    assert wrap_angle(math.pi) == -math.pi
    assert math.isclose(wrap_angle(3 * math.pi / 2), -math.pi / 2)
    assert math.isclose(wrap_angle(-0.1), -0.1)


def test_compose_translates_in_the_parent_frame():
    a = Pose2(1.0, 2.0, math.pi / 2)
    b = Pose2(1.0, 0.0, 0.0)
    c = a @ b
    assert math.isclose(c.x_m, 1.0, abs_tol=1e-12) and math.isclose(c.y_m, 3.0)
    assert math.isclose(c.yaw_rad, math.pi / 2)


@given(poses, poses)
def test_between_then_compose_round_trips(a, b):
    c = a @ a.between(b)
    assert math.isclose(c.x_m, b.x_m, abs_tol=1e-6) and math.isclose(c.y_m, b.y_m, abs_tol=1e-6)
    assert abs(wrap_angle(c.yaw_rad - b.yaw_rad)) < 1e-9


@given(poses)
def test_move_puts_a_polygon_where_apply_puts_its_vertices(a):
    ring = np.array([[0.0, 0.0], [4.0, -1.0], [3.0, 2.5], [0.5, 1.0]])
    moved = a.move(shapely.Polygon(ring))
    assert moved.is_valid and math.isclose(moved.area, shapely.Polygon(ring).area, rel_tol=1e-9)
    assert np.array_equal(np.asarray(moved.exterior.coords)[:-1], a.apply(ring))


@given(poses)
def test_inverse_undoes_apply(a):
    pts = np.array([[0.0, 0.0], [1.5, -2.0], [10.0, 3.0]])
    back = a.inverse().apply(a.apply(pts))
    assert np.allclose(back, pts, atol=1e-6)


def test_grouped_points_move_the_same_through_poses_or_their_rows():
    """Poses given as rows of x, y, yaw (as the graph's cached walks hold them) move each group
    to the bit as the Pose2 objects do, and each group through its own pose."""
    rng = np.random.default_rng(5)
    frames = [Pose2(*rng.uniform(-5, 5, 2), rng.uniform(-3, 3)) for _ in range(4)]
    groups = [rng.uniform(-2, 2, (n, 2)) for n in (3, 0, 5, 1)]
    rows = np.array([(f.x_m, f.y_m, f.yaw_rad) for f in frames])
    by_objects, by_rows = apply_grouped(frames, groups), apply_grouped(rows, groups)
    assert np.array_equal(by_objects, by_rows)
    assert np.allclose(by_rows[3:8], frames[2].apply(groups[2]), atol=1e-12)


def test_first_contact_is_where_and_which_point_the_disc_would_touch():
    pts = np.array([[2.0, 0.0], [1.0, 0.5], [-1.0, 0.0]])
    # Straight at the point 2 m ahead: the disc touches it after 2 - r.
    travel, i = first_contact(pts[:1], (1.0, 0.0), 0.3)
    assert travel == pytest.approx(1.7) and i == 0
    # A point 0.5 m to the side is passed by a 0.3 m disc, touched by a 0.6 m one.
    assert first_contact(pts[1:2], (1.0, 0.0), 0.3) == (math.inf, -1)
    assert first_contact(pts[1:2], (1.0, 0.0), 0.6)[0] == pytest.approx(1.0 - math.sqrt(0.36 - 0.25))
    # Behind does not count; the direction's length does not matter.
    assert first_contact(pts[2:], (1.0, 0.0), 0.3) == (math.inf, -1)
    travel, i = first_contact(pts, (5.0, 0.0), 0.3)
    assert travel == pytest.approx(1.7) and i == 0
    assert first_contact(pts, (0.0, 0.0), 0.3) == (math.inf, -1)
    # Of several in the way, the first touched: the side point for the wide disc.
    travel, i = first_contact(pts, (1.0, 0.0), 0.6)
    assert travel == pytest.approx(1.0 - math.sqrt(0.36 - 0.25)) and i == 1


def _segments_and_points(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    segments = rng.uniform(-5.0, 5.0, size=(9, 2, 2))
    segments[3, 1] = segments[3, 0]  # a wall seen as one point
    points = np.vstack((rng.uniform(-7.0, 7.0, size=(40, 2)), segments[:, 0], segments[5:7].mean(axis=1)))
    return segments, points


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_distances_to_segments_are_shapelys(seed):
    segments, points = _segments_and_points(seed)
    lines = shapely.linestrings(segments)
    expected = shapely.distance(shapely.points(points)[:, None], lines[None, :])
    closest, t = closest_on_segments(points, segments)
    assert closest.shape == (points.shape[0], segments.shape[0], 2)
    assert np.all((t >= 0.0) & (t <= 1.0))
    # Each closest point lies on its segment, as far from the point as shapely says.
    assert np.allclose(shapely.distance(shapely.points(closest), lines[None, :]), 0.0, atol=1e-9)
    assert np.allclose(np.hypot(*(points[:, None, :] - closest).transpose(2, 0, 1)), expected, atol=1e-9)
    assert np.allclose(point_segment_distances(points, segments), expected, atol=1e-9)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_match_pairs_each_point_with_its_nearest_wall(seed):
    walls, points = _segments_and_points(seed)
    dist, closest, normals, at_end = _WallTable.of(walls).nearest(points)
    expected = shapely.distance(shapely.points(points)[:, None], shapely.linestrings(walls)[None, :]).min(axis=1)
    assert np.allclose(dist, expected, atol=1e-9)
    assert np.allclose(np.hypot(*(points - closest).T), dist, atol=1e-9)
    apart = dist > 1e-9  # a point on a wall seen as one point has no direction from it
    assert np.allclose(np.hypot(*normals[apart].T), 1.0)
    ends = walls.reshape(-1, 2)
    assert np.array_equal(
        at_end, np.isclose(np.hypot(*(closest[:, None] - ends[None]).transpose(2, 0, 1)).min(axis=1), 0.0, atol=1e-12)
    )
    # Off a wall's end the normal points from the wall to the point (the residual is a distance);
    # beside it, it is the wall's own normal, so the residual along it is the whole distance.
    off = points - closest
    assert np.allclose(np.abs(np.einsum("nk,nk->n", normals, off)), dist, atol=1e-9)
