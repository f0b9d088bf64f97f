"""Paths through known free space: through doors, centred in them, never through walls or unknown."""

import numpy as np
import pytest
import shapely

from companion.core.free_space_grid import FreeSpaceGrid, GridParams

CLEARANCE_M = 0.4


def corridor_and_room(door_width_m: float) -> tuple[shapely.Geometry, np.ndarray]:
    """A corridor (y 0..2) and a room above it (y 2.1..6) joined by a door centred at x = 6."""
    lo, hi = 6.0 - door_width_m / 2, 6.0 + door_width_m / 2
    free = shapely.union_all([shapely.box(0, 0, 10, 2), shapely.box(4, 2.1, 8, 6), shapely.box(lo, 1.9, hi, 2.2)])
    walls = np.array([[[4.0, 2.0], [lo, 2.0]], [[hi, 2.0], [8.0, 2.0]]])
    return free, walls


def wall_clearance(path: np.ndarray, start: np.ndarray, free: shapely.Geometry) -> float:
    line = shapely.LineString(np.vstack((start, path)))
    return float(shapely.distance(line, free.boundary))


def test_path_goes_through_the_door_and_keeps_clear_of_its_jambs():
    free, walls = corridor_and_room(1.2)
    start, goal = np.array([1.0, 1.0]), np.array([7.0, 5.0])
    path = FreeSpaceGrid.build(free, walls, CLEARANCE_M).reach_from(start).path_to(goal)
    assert path is not None
    np.testing.assert_allclose(path[-1], goal)
    assert shapely.LineString(np.vstack((start, path))).within(free)
    # Half a cell of rasterisation is the only slack on the clearance.
    assert wall_clearance(path, start, free) >= CLEARANCE_M - 0.08
    # The corner before the door is moved off the jamb, towards the door's middle.
    crossing = [p for p in path if 1.5 <= p[1] <= 2.5]
    assert crossing, f"no waypoint at the door: {path}"
    assert all(abs(p[0] - 6.0) <= 0.2 for p in crossing)


def test_a_door_narrower_than_the_vehicle_needs_has_no_path():
    free, walls = corridor_and_room(0.6)
    reach = FreeSpaceGrid.build(free, walls, CLEARANCE_M).reach_from(np.array([1.0, 1.0]))
    assert reach is not None
    assert reach.path_to(np.array([7.0, 5.0])) is None
    assert reach.path_to(np.array([9.0, 1.0])) is not None  # the corridor itself is still reachable


def test_behind_a_door_too_narrow_the_nearest_reached_place_is_in_front_of_it():
    """The planner's approach: as near a place out of reach as the free space leads."""
    free, walls = corridor_and_room(0.6)
    reach = FreeSpaceGrid.build(free, walls, CLEARANCE_M).reach_from(np.array([1.0, 1.0]))
    assert reach is not None
    nearest = reach.nearest_to(np.array([[6.0, 4.0]]))
    assert nearest is not None and nearest.shape == (1, 2)
    near = nearest[0]
    assert abs(near[0] - 6.0) <= 0.1 and 1.4 <= near[1] < 2.0  # at the door, not through it
    assert reach.path_to(near) is not None


def test_obstacle_points_from_the_live_scan_block_a_path():
    free, walls = corridor_and_room(1.2)
    grid = FreeSpaceGrid.build(free, walls, CLEARANCE_M)
    blocking = np.column_stack((np.full(20, 5.0), np.linspace(0.0, 2.0, 20)))  # across the corridor
    reach = grid.with_blocked_points(blocking).reach_from(np.array([1.0, 1.0]))
    assert reach is not None
    assert reach.path_to(np.array([9.0, 1.0])) is None
    assert grid.reach_from(np.array([1.0, 1.0])).path_to(np.array([9.0, 1.0])) is not None


@pytest.mark.parametrize("start", [(1.0, 0.3), (0.2, 1.0)])
def test_a_start_closer_to_a_wall_than_the_clearance_still_finds_its_way_out(start):
    free, walls = corridor_and_room(1.2)
    reach = FreeSpaceGrid.build(free, walls, CLEARANCE_M).reach_from(np.array(start))
    assert reach is not None
    path = reach.path_to(np.array([9.0, 1.0]))
    assert path is not None
    np.testing.assert_allclose(path[-1], [9.0, 1.0])


def test_a_goal_in_unknown_space_is_not_reachable():
    free, walls = corridor_and_room(1.2)
    reach = FreeSpaceGrid.build(free, walls, CLEARANCE_M).reach_from(np.array([1.0, 1.0]))
    assert reach is not None
    assert reach.path_to(np.array([2.0, 5.0])) is None  # beside the room, never seen


def test_views_rasterised_in_batches_give_the_cells_of_their_union():
    """The grid of a neighbourhood is built from its views without their union (in batches of
    1, 2, 3, ... views, each testing only the cells earlier ones left): the same free cells, but
    for centres within a millimetre of an edge."""
    rng = np.random.default_rng(3)
    views = []
    for _ in range(12):
        x, y, yaw = rng.uniform(0, 6), rng.uniform(0, 4), rng.uniform(-np.pi, np.pi)
        angles = yaw + np.linspace(-np.pi / 4, np.pi / 4, 24)
        ranges = rng.uniform(2.0, 5.0, angles.size)
        fan = np.column_stack((x + ranges * np.cos(angles), y + ranges * np.sin(angles)))
        views.append(shapely.Polygon(np.vstack(([x, y], fan))))
    views_arr = np.array(views, dtype=object)
    walls = np.zeros((0, 2, 2))
    one_by_one = FreeSpaceGrid.build(views_arr, walls, CLEARANCE_M)
    of_union = FreeSpaceGrid.build(shapely.union_all(views_arr, grid_size=1e-3), walls, CLEARANCE_M)
    assert one_by_one.origin_xy == of_union.origin_xy
    assert one_by_one.free.shape == of_union.free.shape
    assert np.count_nonzero(one_by_one.free != of_union.free) <= 0.002 * one_by_one.free.size


def test_a_sliver_between_two_views_is_no_wall():
    """Two views whose edges lie 0.2 mm apart, a column of cell centres in the gap: their union
    is one piece, and so is the grid (one blocked column, eroded, would close the way)."""
    cell = GridParams().cell_m
    x0 = -(CLEARANCE_M + 2 * cell)  # the grid's first cell centre, for views starting at x = 0
    gap_x = x0 + 25 * cell
    views = np.array([shapely.box(0, 0, gap_x - 1e-4, 3), shapely.box(gap_x + 1e-4, 0, 6, 3)], dtype=object)
    grid = FreeSpaceGrid.build(views, np.zeros((0, 2, 2)), CLEARANCE_M)
    assert grid.origin_xy[0] == pytest.approx(x0)
    assert grid.reach_from(np.array([1.5, 1.5])).path_to(np.array([4.5, 1.5])) is not None


def test_lines_free_in_one_pass_says_what_each_line_says_alone():
    """The batched line-of-sight test (path shortening asks it of every point ahead at once)
    must answer for each end exactly as the one-line test does, on lines that graze the
    door's jambs, cross walls, leave the grid, or have no length."""
    free, walls = corridor_and_room(1.0)
    grid = FreeSpaceGrid.build(free, walls, CLEARANCE_M)
    rng = np.random.default_rng(7)
    for _ in range(40):
        start = rng.uniform([-1.0, -1.0], [11.0, 7.0])
        near_door = rng.uniform([5.0, 1.5], [7.0, 3.0], size=(30, 2))  # lines that graze a jamb
        ends = np.vstack((rng.uniform([-1.0, -1.0], [11.0, 7.0], size=(30, 2)), near_door, start))
        batch = grid.lines_free(start, ends)
        alone = np.array([grid.line_free(start, e) for e in ends])
        np.testing.assert_array_equal(batch, alone)
    assert grid.lines_free(np.array([1.0, 1.0]), np.array([[9.0, 1.0]]))[0]  # along the corridor
    assert not grid.lines_free(np.array([1.0, 1.0]), np.array([[5.0, 5.0]]))[0]  # through the wall
