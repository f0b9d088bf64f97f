"""Which frontier vertices have only a sliver of unseen space beyond them (slivers.py).

Each case: one frontier vertex at the origin facing +x (its outward normal), the space the views
saw as polygons, and the walls they saw, all in one frame."""

import numpy as np
import shapely

from companion.core.slivers import SliverParams, sliver_vertices

VERTEX = np.array([[0.0, 0.0]])
OUTWARD = np.array([[1.0, 0.0]])


def judge(seen: list[shapely.Geometry], walls: list[tuple[tuple[float, float], tuple[float, float]]]) -> bool:
    shapes = np.array(seen, dtype=object)
    segments = np.array(walls, dtype=np.float64).reshape(-1, 2, 2)
    return bool(sliver_vertices(VERTEX, OUTWARD, shapes, segments, SliverParams())[0])


BEHIND = shapely.box(-3.0, -3.0, 0.0, 3.0)  # the view the vertex belongs to, all behind it


def test_a_strip_narrower_than_the_width_between_seen_space_and_a_wall_is_a_sliver():
    # Seen space up to x = 0.2 beyond the vertex (and to either side), a wall at x = 0.45:
    # the unseen strip between is 0.25 m wide.
    seen = [BEHIND, shapely.box(0.0, -3.0, 0.2, 3.0)]
    assert judge(seen, [((0.45, -3.0), (0.45, 3.0))])
    # The same strip 0.8 m wide is worth a look.
    assert not judge(seen, [((1.0, -3.0), (1.0, 3.0))])


def test_open_unseen_space_beyond_is_no_sliver():
    # A range-limit vertex: nothing beyond it seen, no wall known.
    assert not judge([BEHIND], [])


def test_a_gap_between_two_walls_ends_is_a_sliver_only_when_too_narrow_to_see_through():
    # Seen space 0.4 m beyond the vertex, then two walls across with a gap at y = 0; behind them
    # unseen space (inside a block where the walls meet at a corner the scans missed).
    seen = [BEHIND, shapely.box(0.0, -3.0, 0.4, 3.0)]
    narrow = [((0.45, -3.0), (0.45, -0.1)), ((0.45, 0.1), (0.45, 3.0))]
    wide = [((0.45, -3.0), (0.45, -0.5)), ((0.45, 0.5), (0.45, 3.0))]  # a 1 m door
    assert judge(seen, narrow)
    assert not judge(seen, wide)


def test_a_thin_seen_strip_does_not_hide_the_unseen_space_behind_it():
    # Another view saw only a sliver beyond the vertex (as one seen through a door at a grazing
    # angle, or one drift slid there): the space behind it is still unseen and wide.
    seen = [BEHIND, shapely.box(0.0, -3.0, 0.3, 3.0)]
    assert not judge(seen, [])


def test_space_behind_a_wall_is_not_the_vertexs():
    # A wall right beyond the vertex across the whole window: the unseen space past it is not
    # reached from the vertex, and what is left (a 0.25 m strip) is a sliver.
    seen = [BEHIND]
    assert judge(seen, [((0.25, -3.0), (0.25, 3.0))])


def test_every_vertex_is_judged_in_one_call():
    # Two vertices facing opposite ways: one into open space, one at a wall 0.2 m away.
    vertices = np.array([[0.0, 0.0], [5.0, 0.0]])
    outward = np.array([[-1.0, 0.0], [1.0, 0.0]])
    shapes = np.array([shapely.box(0.0, -3.0, 5.0, 3.0)], dtype=object)
    walls = np.array([((5.2, -3.0), (5.2, 3.0))])
    assert sliver_vertices(vertices, outward, shapes, walls, SliverParams()).tolist() == [False, True]


def test_a_zero_reach_turns_the_test_off():
    seen = np.array([BEHIND], dtype=object)
    walls = np.array([((0.15, -3.0), (0.15, 3.0))])
    assert not sliver_vertices(VERTEX, OUTWARD, seen, walls, SliverParams(reach_m=0.0))[0]
