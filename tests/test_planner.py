"""Frontier planner rules, one at a time."""

import dataclasses
import functools
import math
from collections.abc import Callable

import numpy as np
import pytest
import shapely

from companion.core.fov_polygon import FovPolygon, PolygonParams, VertexKind, scan_to_polygon
from companion.core.frontiers import FrontierKey, run_sizes_m, targetable_indices
from companion.core.geometry import Pose2
from companion.core.local_map import Keyframe, LocalMap, MapParams
from companion.core.messages import DepthScan
from companion.core.planner import Decision, FrontierPlanner, Mode, PlannerParams, _Route

BEARINGS = np.linspace(-math.pi / 4, math.pi / 4, 64)


def test_a_frontier_found_out_of_reach_step_after_step_counts_one_try_per_cooldown():
    """At a keyframe's origin a goal dropped as blocked is still cooling down, so it is found out
    of reach at every step until then: that is one failed try, not one per step (two would set it
    aside before it was ever tried again)."""
    planner = FrontierPlanner(PlannerParams(max_attempts=2, blocked_cooldown_s=5.0))
    key = FrontierKey(7, 3)
    for k in range(30):
        planner._failed(key, 100.0 + 0.1 * k, at_origin=True)
    assert planner.attempts[key] == 1 and key not in planner.set_aside
    planner._failed(key, 105.5, at_origin=True)  # tried again after the cooldown, and out of reach again
    assert planner.attempts[key] == 2 and key in planner.set_aside


def test_a_cooling_goal_is_tried_again_from_its_own_keyframes_origin():
    """A goal dropped as blocked cools down, but the route back to its keyframe is another way to
    it: from that origin it is taken, not found 'out of reach' untried (a failed try counted
    there, twice in a row, set aside frontiers that were never out of reach)."""
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    planner = FrontierPlanner()
    keys = [FrontierKey(kf.keyframe_id, int(i)) for i in targetable_indices(kf, planner.params.min_frontier_size_m)]
    assert keys
    planner._cooling = {k: 105.0 for k in keys}  # all dropped as blocked a moment ago
    decision = planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0)
    assert decision.mode is Mode.EXPLORING and decision.goal in keys
    assert not planner.attempts


def test_a_vehicle_just_behind_its_keyframes_apex_still_takes_the_keyframes_frontiers():
    """Flown back to a keyframe, the vehicle stops within reach of its origin, maybe a little
    behind it, outside the view's wedge. The disc its body covers is free by its presence, so a
    path from there counts as in known free space from that disc's edge on: otherwise every path
    left the view at once, and each frontier counted failed tries until all were set aside (the
    rotunda, seed 14: at 10 s, coverage 0.10)."""
    ranges = 2.0 / np.cos(BEARINGS)  # a wall across the way, 2 m ahead: only the sides are open
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, ranges, 5.0)))
    assert targetable_indices(kf, PlannerParams().min_frontier_size_m).size
    for behind_m in (0.0, 0.1, 0.2):
        planner = FrontierPlanner()
        decision = planner.plan(m, kf.keyframe_id, Pose2(-behind_m, 0.02, math.pi), 100.0)
        assert decision.mode is Mode.EXPLORING and decision.goal is not None, behind_m
        assert not planner.attempts


def test_a_frontier_seen_through_a_door_too_narrow_to_fly_is_approached_not_just_failed():
    """From its keyframe's origin nothing behind a 0.34 m gap is in reach: that counts a failed
    try, and the vehicle then goes as near as the free space leads (in front of the gap) to look
    again, without closing the frontier it only came nearer to."""
    ranges = 2.0 / np.cos(BEARINGS)  # a wall across the way, 2 m ahead
    gap = (BEARINGS > 0.25) & (BEARINGS < 0.40)
    ranges[gap] = 5.0  # seen through the gap to the sensor's range
    polygon = scan_to_polygon(
        DepthScan(0.0, BEARINGS, ranges, 5.0),
        PolygonParams(side_frontier_spacing_m=0.0, occlusion_frontier_spacing_m=0.0),
    )
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), polygon)
    at_jambs = np.flatnonzero(np.hypot(*polygon.vertices_xy.T) < 3.0)
    m.close_frontiers(kf.keyframe_id, at_jambs)  # looked at already: only the far ones are left
    planner = FrontierPlanner()
    decision = planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0)
    assert decision.mode is Mode.EXPLORING
    assert planner.goal is not None and planner.goal.approach
    assert planner.attempts and all(n == 1 for n in planner.attempts.values())
    gx, gy = planner.goal.local_xy
    assert 0.8 <= gx < 2.0 - planner.params.clearance_m + 0.1  # in front of the wall, short of it
    vertex = kf.polygon.vertices_xy[planner.goal.key.index]
    assert np.hypot(*(vertex - (gx, gy))) <= np.hypot(*vertex) - planner.params.approach_gain_m
    # Arrived and looked: a new view is asked for, and the frontier stays open for it to judge.
    there = Pose2(gx, gy, planner.goal.look_local_rad)
    assert planner.plan(m, kf.keyframe_id, there, 101.0).want_keyframe
    key = planner.goal.key
    planner.plan(m, kf.keyframe_id, there, 102.5)
    assert planner.goal is None or planner.goal.key != key
    assert kf.kinds[key.index] == VertexKind.FRONTIER


def test_a_frontier_behind_a_door_the_grid_closes_at_the_full_clearance_is_tried_at_a_legs():
    """At a keyframe's origin no straight path reaches the frontiers behind a gap, and the
    free-space grid at the full clearance finds none either (a 0.9 m door rasterised at 0.4 m may
    close): the grid at a leg's clearance (body radius and leg margin, what each leg of the path
    is held to as it is flown) is asked next, and its path taken. Without it, a room behind a 0.9 m door seen from the
    corridor had its frontiers set aside (apartment seed 15, coverage 0.972)."""
    ranges = 2.0 / np.cos(BEARINGS)  # a wall across the way, 2 m ahead
    ranges[(BEARINGS > 0.25) & (BEARINGS < 0.40)] = 5.0  # seen through a gap to the sensor's range
    polygon = scan_to_polygon(
        DepthScan(0.0, BEARINGS, ranges, 5.0),
        PolygonParams(side_frontier_spacing_m=0.0, occlusion_frontier_spacing_m=0.0),
    )
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), polygon)
    m.close_frontiers(kf.keyframe_id, np.flatnonzero(np.hypot(*polygon.vertices_xy.T) < 3.0))
    asked: list[float] = []
    params = PlannerParams()
    full, leg = params.clearance_m, params.body_radius_m + params.leg_margin_m

    class ThroughTheGap:
        def path_to(self, goal_xy: np.ndarray, snap: bool = False) -> np.ndarray:
            return np.array([[1.8, 0.6], goal_xy])

    class GridClosedAtTheFullClearance(FrontierPlanner):
        def _reach(self, view: object, here: np.ndarray, clearance_m: float | None = None) -> ThroughTheGap | None:  # type: ignore[override]
            asked.append(full if clearance_m is None else clearance_m)
            return ThroughTheGap() if asked[-1] == leg else None

    def at_the_origin(**live: np.ndarray) -> tuple[GridClosedAtTheFullClearance, Decision]:
        """Flown back to the keyframe's origin by a route, where its frontiers are taken."""
        planner = GridClosedAtTheFullClearance(params)
        planner.route = _Route([kf.keyframe_id], kf.keyframe_id)
        planner._arrived_at = kf.keyframe_id
        return planner, planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0, **live)

    planner, decision = at_the_origin()
    assert asked == [full, full, leg]  # as rapid selection (full only), then at the origin (both)
    assert decision.mode is Mode.EXPLORING and planner.goal is not None and not planner.goal.approach
    assert planner.goal.path is not None and np.allclose(planner.goal.path[0], (1.8, 0.6))
    assert not planner.attempts
    # A path the newest scan sees passing a return closer than a leg may pass is not taken: such
    # goals were dropped at once, one after another, for 20 minutes (offices2 seed 4).
    planner, _ = at_the_origin(live_obstacles_xy=np.array([[1.0, 0.45]]))
    assert planner.goal is None or planner.goal.path is None or not np.allclose(planner.goal.path[0], (1.8, 0.6))


def test_every_goal_faces_its_frontier_vertex():
    """From a goal on the vertex's ray the vehicle looks at the vertex, not along its normal: a
    shadow edge's vertex (normal across the ray) lay 90 degrees off the view taken on arrival,
    which then closed it and its neighbours as looked at, and a room behind a door was never
    entered (lshape seed 6 ended `complete` at coverage 0.96)."""
    ranges = 2.0 / np.cos(BEARINGS)  # a wall 2 m ahead with a gap seen through to 5 m
    gap = (BEARINGS > 0.1) & (BEARINGS < 0.5)
    ranges[gap] = 5.0
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.3), scan_to_polygon(DepthScan(0.0, BEARINGS, ranges, 5.0)))
    planner = FrontierPlanner()
    view = m.view(kf.keyframe_id)
    candidates = planner._candidates(m, view, Pose2(0.0, 0.0, 0.3), np.zeros(2), dense=True)
    assert len(candidates) > 10
    v, n = kf.polygon.vertices_xy, kf.polygon.outward_xy
    off_normal = 0
    for c in candidates:
        to_vertex = v[c.key.index] - c.goal_xy
        assert abs(math.remainder(c.look_rad - math.atan2(to_vertex[1], to_vertex[0]), math.tau)) < 1e-9
        normal = math.atan2(n[c.key.index][1], n[c.key.index][0])
        off_normal += abs(math.remainder(c.look_rad - normal, math.tau)) > 0.3
    assert off_normal > 0  # some goals (on the ray of a shadow edge's vertex) look off the normal


def test_no_goal_repeats_its_keyframes_own_view():
    """A jamb 0.8 m ahead: its occlusion vertex lies within the standoff of the keyframe's origin,
    so its goal on the ray is the origin itself, facing about the keyframe's heading, which is
    the view the keyframe already took. No such goal is offered (flown to, it was looked at and
    closed, the view taken on arrival found the vertex again, and a vehicle turned on one spot
    for 20 minutes); goals at the origin that turn to see past the field of view's side stay."""
    ranges = np.where(BEARINGS < 0.1, 0.8 / np.cos(BEARINGS), 5.0)
    m = LocalMap()
    behind = m.add_keyframe(
        0.0, Pose2(-1.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 1.5), 5.0))
    )
    scan = DepthScan(0.1, BEARINGS, ranges, 5.0)
    kf = m.add_keyframe(0.1, Pose2(0.0, 0.0, 0.0), scan_to_polygon(scan), (behind.keyframe_id, Pose2(1.0, 0.0, 0.0)))
    v = kf.polygon.vertices_xy[targetable_indices(kf, 0.3)]
    near_ahead = (np.hypot(v[:, 0], v[:, 1]) < 1.0) & (np.abs(np.arctan2(v[:, 1], v[:, 0])) < 0.5)
    assert near_ahead.any()  # the jamb's occlusion vertex, a frontier within the standoff
    planner = FrontierPlanner()
    candidates = planner._candidates(m, m.view(kf.keyframe_id), Pose2(0.0, 0.0, 0.0), np.zeros(2), dense=True)
    at_origin = [c for c in candidates if c.key.keyframe_id == kf.keyframe_id and np.hypot(*c.goal_xy) <= 0.3]
    assert at_origin  # turning on the spot to see past the side edges is still a goal
    assert all(abs(c.look_rad) >= 0.5 for c in at_origin)


def test_a_goal_is_not_dropped_on_the_spot_it_was_taken_unless_the_newest_scan_blocks_it():
    """A view taken a step after a goal was committed, on the same spot, has its own
    neighbourhood, which may judge the path blocked where the one it was taken in did not:
    dropping it there made a vehicle go back to the old keyframe, take a goal, take a view,
    drop it, for two minutes. Only the newest scan can drop it before the vehicle moves."""
    no_sides = PolygonParams(side_frontier_spacing_m=0.0)
    wall_scan = DepthScan(0.0, BEARINGS, 1.5 / np.cos(BEARINGS), 5.0)  # a wall across, 1.5 m ahead
    wall_returns = np.column_stack((np.full(64, 1.5), 1.5 * np.tan(BEARINGS)))

    def committed_then_walled() -> tuple[LocalMap, int, FrontierPlanner, FrontierKey]:
        m = LocalMap()
        scan_5m = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
        a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(scan_5m, no_sides))
        planner = FrontierPlanner()
        assert planner.plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.EXPLORING
        assert planner.goal is not None and np.hypot(*planner.goal.local_xy) > 2.0  # beyond the wall
        b = m.add_keyframe(0.1, Pose2(0.0, 0.0, 0.0), scan_to_polygon(wall_scan, no_sides), (a.keyframe_id, Pose2()))
        return m, b.keyframe_id, planner, planner.goal.key

    m, b, planner, key = committed_then_walled()
    planner.plan(m, b, Pose2(0.0, 0.0, 0.0), 0.1)
    assert planner.goal is not None and planner.goal.key == key  # the map alone: kept on the spot
    planner.plan(m, b, Pose2(0.5, 0.0, 0.0), 0.2)
    assert planner.goal is None or planner.goal.key != key  # moved: the map judges it again
    m, b, planner, key = committed_then_walled()
    planner.plan(m, b, Pose2(0.0, 0.0, 0.0), 0.1, wall_returns)
    assert planner.goal is None or planner.goal.key != key  # the newest scan sees it blocked


def _fragment_here_run_there(
    open_there: int, at_side: bool = False, beside_seen: bool = False
) -> tuple[LocalMap, Keyframe, Keyframe]:
    """Keyframe A sees 5 m of free space ahead, every frontier vertex closed as a wall but one in
    the middle of its range arc: a gap seen through, whose run spans half of each edge (about
    0.37 m; the arc's vertices lie about 0.37 m apart). Or (``at_side``) but one on its field of
    view's side, 0.4 m from the next (a run of 0.4 m, not at the range limit); ``beside_seen``:
    the arc's vertex before it closed as seen, not as a wall. Keyframe C, 40 m
    on past B (which sees nothing open), is closed the same way but for ``open_there`` vertices
    of its arc."""
    scan_5m = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
    m = LocalMap()

    def add(stamp_s: float, y_m: float, open_vertices: int, side: bool = False, seen: bool = False) -> Keyframe:
        parent = None if not m.keyframes else (max(m.keyframes), Pose2(0.0, 20.0, 0.0))
        polygon = scan_to_polygon(scan_5m, PolygonParams(side_frontier_spacing_m=0.4 if side else 1.0))
        kf = m.add_keyframe(stamp_s, Pose2(0.0, y_m, 0.0), polygon, parent)
        idx = np.flatnonzero(kf.kinds == VertexKind.FRONTIER)
        arc = idx[np.hypot(*kf.polygon.vertices_xy[idx].T) > 4.9]
        if side:
            keep = idx[np.argmin(np.abs(np.hypot(*kf.polygon.vertices_xy[idx].T) - 2.5))][None]
        else:
            mid = arc.size // 2 - open_vertices // 2
            keep = arc[mid : mid + open_vertices]
            if seen:
                m.close_frontiers(kf.keyframe_id, arc[mid - 1 : mid])
        m.close_frontiers(kf.keyframe_id, np.setdiff1d(idx, keep), VertexKind.OBSTACLE)
        return kf

    a, _, c = add(0.0, 0.0, 1, at_side, beside_seen), add(1.0, 20.0, 0), add(2.0, 40.0, open_there)
    return m, a, c


def test_a_frontier_fragment_waits_until_no_longer_run_is_left_and_is_near():
    """A fragment (a run under 0.6 m) in view is passed over while a longer run is left anywhere:
    the vehicle flies back along the pose graph to C's 0.75 m run instead. With nothing longer
    left it is flown to from within 4 m (a fragment may be the way on: never flown to, runs under
    0.8 m ended a spiral corridor's exploration at coverage 0.13), and from farther only if it
    lies at the sensor's range limit (a corridor seen end-on). Without loop closures, where
    0.6 m was not measured, 0.3 m holds (companion.app.planner_params)."""
    from companion.app import planner_params

    m, a, c = _fragment_here_run_there(2)
    sizes = run_sizes_m(a.kinds, a.polygon.vertices_xy)
    params = PlannerParams()
    assert params.fragment_size_m < sizes.max() < params.min_frontier_size_m
    assert run_sizes_m(c.kinds, c.polygon.vertices_xy).max() > params.min_frontier_size_m
    planner = FrontierPlanner(params)
    decision = planner.plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 0.0)
    assert decision.mode is Mode.BACKTRACKING and planner.route is not None
    assert planner.route.target_keyframe == c.keyframe_id
    without = FrontierPlanner(planner_params(False)).plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 0.0)
    assert without.mode is Mode.EXPLORING and without.goal is not None and without.goal.keyframe_id == a.keyframe_id
    m, a, c = _fragment_here_run_there(0)
    decision = FrontierPlanner(params).plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 0.0)
    assert decision.mode is Mode.EXPLORING and decision.goal is not None
    assert decision.goal.keyframe_id == a.keyframe_id and sizes[decision.goal.index] > 0.0
    never = dataclasses.replace(params, fragment_size_m=params.min_frontier_size_m)  # no fragment ever
    assert FrontierPlanner(never).plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.COMPLETE
    # From B, 20 m away: a fragment on the field of view's side is not flown to (exploration is
    # complete), nor one at the range limit beside space seen, nor A's, whose closed neighbours
    # lie by no wall (not an opening: see the test below for one that is).
    b = m.graph.path(a.keyframe_id, c.keyframe_id)[1]
    m_side, a_side, _ = _fragment_here_run_there(0, at_side=True)
    side_sizes = run_sizes_m(a_side.kinds, a_side.polygon.vertices_xy)
    assert params.fragment_size_m < side_sizes.max() < params.min_frontier_size_m
    assert not a_side.polygon.at_range_limit[np.argmax(side_sizes)]
    assert FrontierPlanner(params).plan(m_side, b, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.COMPLETE
    m_seen, a_seen, _ = _fragment_here_run_there(0, beside_seen=True)
    open_seen = np.flatnonzero(a_seen.kinds == VertexKind.FRONTIER)
    assert open_seen.size == 1 and a_seen.polygon.at_range_limit[open_seen[0]]
    assert FrontierPlanner(params).plan(m_seen, b, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.COMPLETE
    assert FrontierPlanner(params).plan(m, b, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.COMPLETE


def test_a_goal_whose_run_other_views_closed_down_to_a_remnant_is_still_flown_to():
    """Other views closed the frontier round the goal's vertex, down to a remnant shorter than a
    new goal is worth; the vertex itself stays open. It is still flown to: a door seen at an
    angle closes that way, and giving such goals up left a room behind a 1.5 m door unseen
    (apartment seed 4 ended `complete` at coverage 0.78)."""
    m = LocalMap()
    a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    planner = FrontierPlanner()
    assert planner.plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.EXPLORING
    assert planner.goal is not None
    key = planner.goal.key
    others = np.flatnonzero((a.kinds == VertexKind.FRONTIER) & (np.arange(a.kinds.size) != key.index))
    m.close_frontiers(a.keyframe_id, others)
    assert a.kinds[key.index] == VertexKind.FRONTIER
    assert key.index not in targetable_indices(a, planner.params.min_frontier_size_m)
    decision = planner.plan(m, a.keyframe_id, Pose2(0.3, 0.0, 0.0), 0.1)
    assert planner.goal is not None and planner.goal.key == key and decision.goal == key


def test_a_frontier_a_view_beyond_the_neighbourhood_saw_past_is_not_flown_to():
    """The vehicle went round the block: a later view C saw past A's frontier ahead, but the
    graph reaches C from A only through a view that overlaps neither, so C is not in A's
    neighbourhood. The candidate is checked along the graph before it is taken."""
    scan_5m = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
    scan_1m = DepthScan(0.0, BEARINGS, np.full(64, 1.0), 5.0)
    m = LocalMap(MapParams(neighbourhood_bridge_hops=0))  # B stands for a detour longer than the walk bridges
    a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(scan_5m))
    b = m.add_keyframe(1.0, Pose2(0.0, 20.0, 0.0), scan_to_polygon(scan_1m), (a.keyframe_id, Pose2(0.0, 20.0, 0.0)))
    c_pose_in_b = Pose2(0.0, 20.0, 0.0).between(Pose2(6.0, 0.0, math.pi))
    m.add_keyframe(2.0, Pose2(6.0, 0.0, math.pi), scan_to_polygon(scan_5m), (b.keyframe_id, c_pose_in_b))
    assert m.neighbourhood(a.keyframe_id) == {}
    ahead = np.flatnonzero((a.kinds == VertexKind.FRONTIER) & (np.abs(a.polygon.vertices_xy[:, 1]) < 0.5))
    assert ahead.size  # open before the check
    planner = FrontierPlanner()
    decision = planner.plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 10.0)
    assert decision.mode is Mode.EXPLORING and decision.goal is not None
    assert np.all(a.kinds[ahead] == VertexKind.FREE)
    assert decision.goal.index not in ahead


def test_a_path_keeps_from_the_newest_returns_what_the_setpoint_lead_will_keep():
    """A wall drifted onto the vehicle eases the clearance paths keep from the map; from the
    newest returns a path must still keep the body radius and margin (what the setpoint lead
    holds the vehicle to), or the lead stops it on a path the planner thinks clear, for good
    (hotel seed 7 sat 700 s in a doorway). Already closer than that, it may move away."""
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    planner = FrontierPlanner()
    here = np.zeros(2)
    floor = planner.params.body_radius_m + planner.params.leg_margin_m
    jamb = np.array([[0.28, -0.22]])  # a door jamb ahead on the right, 0.36 m away
    planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0, live_obstacles_xy=jamb)
    view = m.view(kf.keyframe_id)
    eased = 0.145  # what a map wall 0.16 m from the vehicle leaves as the required clearance
    straight, centred = np.array([1.5, 0.0]), np.array([1.0, 0.5])
    assert planner._accessible(view, here, straight, eased) is False  # passes the jamb 0.22 m off
    assert planner._accessible(view, here, centred, eased) is True  # keeps more than the floor
    assert planner._leg_blocked(Pose2(0.0, 0.0, 0.0), here, straight, eased)
    # Already 0.2 m from a return: paths keeping 0.19 m from it are allowed (it can move away).
    planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 101.0, live_obstacles_xy=np.array([[0.0, -0.2]]))
    assert planner._live_floor_m == 0.95 * 0.2 < floor
    assert planner._accessible(view, here, np.array([1.5, 0.1]), eased) is True


def test_a_route_leg_grazing_a_wall_goes_round_through_the_newest_scan():
    """In a narrow corridor the next route keyframe may sit (as the drifted graph places it) too
    close to a wall for a straight leg. The planner then aims through the newest scan's free
    space, nearer the keyframe and clear of the returns, rather than count the leg blocked; with
    the way truly closed it finds no such aim."""
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    xs = np.arange(0.2, 3.0, 0.05)
    wall = np.column_stack((xs, np.full(xs.size, 0.45)))  # the corridor's wall, 0.45 m to the left
    corridor = shapely.box(-0.1, -0.9, 3.0, 0.45)
    planner = FrontierPlanner()
    planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0, live_obstacles_xy=wall, live_view=lambda: corridor)
    here, wp = np.zeros(2), np.array([2.0, 0.3])  # 0.15 m from the wall
    required = planner.params.clearance_m
    assert planner._leg_blocked(Pose2(0.0, 0.0, 0.0), here, wp, required)
    aim = planner._sidestep(here, wp, required)
    assert aim is not None
    floor = planner.params.body_radius_m + planner.params.leg_margin_m
    assert np.hypot(*(wp - here)) - np.hypot(*(wp - aim)) >= planner.params.sidestep_gain_m
    assert np.min(np.hypot(*(wall - aim).T)) >= floor
    assert corridor.covers(shapely.LineString([here + 0.05 * aim / np.hypot(*aim), aim]))
    # A wall across the corridor 0.5 m ahead: no aim gets nearer without passing it too close.
    ys = np.arange(-0.9, 0.45, 0.05)
    across = np.vstack((wall, np.column_stack((np.full(ys.size, 0.5), ys))))
    closed = shapely.box(-0.1, -0.9, 0.5, 0.45)
    planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 101.0, live_obstacles_xy=across, live_view=lambda: closed)
    assert planner._sidestep(here, wp, required) is None


def _open_view_with_a_frontier_ahead() -> tuple[LocalMap, Keyframe, FrontierKey]:
    """One keyframe seeing 5 m every way in its field of view, and its frontier vertex straight ahead."""
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    open_idx = targetable_indices(kf, 0.3)
    key = FrontierKey(kf.keyframe_id, int(open_idx[np.argmin(np.abs(kf.polygon.vertices_xy[open_idx, 1]))]))
    return m, kf, key


def test_the_last_leg_of_a_path_through_free_space_is_judged_like_its_other_legs():
    """A goal has a path through the free-space grid because its straight line failed the strict
    test (the whole margin clear); that path's last leg is flown while the newest scan keeps it
    clear of the body radius and leg margin. Asked the strict test again, the last leg dropped
    the goal the step after it was taken (a 0.9 m door's frontiers, one after another, until
    they were set aside). A leg the scan sees blocked still drops it."""
    from companion.core.planner import _Candidate

    m, kf, key = _open_view_with_a_frontier_ahead()
    goal_xy = np.array([3.0, 0.0])
    vehicle = Pose2(0.0, 0.0, 0.0)
    for jamb_y, kept in ((0.35, True), (0.2, False)):
        planner = FrontierPlanner()
        jamb = np.array([[1.5, jamb_y]])
        candidate = _Candidate(key, goal_xy, 0.0, 0.0, path=goal_xy[None, :].copy())
        planner._commit(m, kf.keyframe_id, candidate, np.zeros(2), 100.0)
        view = m.view(kf.keyframe_id)
        required = planner.params.clearance_m
        planner.plan(m, kf.keyframe_id, vehicle, 100.1, live_obstacles_xy=jamb)  # sets the live returns
        assert not planner._accessible(view, np.zeros(2), goal_xy, required)  # the strict test fails
        planner._commit(m, kf.keyframe_id, candidate, np.zeros(2), 100.1)
        decision = planner.plan(m, kf.keyframe_id, vehicle, 100.2, live_obstacles_xy=jamb)
        if kept:
            assert planner.goal is not None and planner.goal.key == key and decision.goal == key
            assert (decision.target.x_m, decision.target.y_m) == (3.0, 0.0)
        else:
            assert decision.goal != key and key in planner._cooling


def test_a_goals_path_leg_grazing_a_return_goes_round_through_the_newest_scan():
    """A leg of a goal's path through free space that the newest scan sees a few centimetres too
    close to a return is flown round through the scan's free space, as a route's leg is, and the
    goal is kept; only with no way round in the scan is it dropped."""
    from companion.core.planner import _Candidate, _segment_clearance

    m, kf, key = _open_view_with_a_frontier_ahead()
    goal_xy = np.array([3.0, 0.0])
    vehicle = Pose2(0.0, 0.0, 0.0)
    jamb = np.array([[1.5, 0.27]])  # 0.27 m off the line: a leg keeps 0.30 m
    for free_space, kept in ((shapely.box(-0.5, -1.5, 4.0, 0.2), True), (shapely.box(-0.5, -0.05, 0.2, 0.05), False)):
        planner = FrontierPlanner()
        candidate = _Candidate(key, goal_xy, 0.0, 0.0, path=goal_xy[None, :].copy())
        planner._commit(m, kf.keyframe_id, candidate, np.zeros(2), 100.0)
        decision = planner.plan(
            m, kf.keyframe_id, vehicle, 100.1, live_obstacles_xy=jamb, live_view=lambda f=free_space: f
        )
        if kept:
            assert planner.goal is not None and planner.goal.key == key and decision.goal == key
            assert planner.goal.path is not None and planner.goal.path.shape[0] == 2
            aim = planner.goal.path[0]
            assert _segment_clearance(np.zeros(2), aim, jamb) >= 0.3  # a leg there is clear of the return
            assert 3.0 - np.hypot(*(goal_xy - aim)) >= planner.params.sidestep_gain_m  # and nearer the goal
            assert np.allclose(planner.goal.path[-1], goal_xy)  # then on to the goal
            target = np.array([decision.target.x_m, decision.target.y_m])
            heading = abs(decision.target.yaw_rad - math.atan2(aim[1], aim[0]))
            assert np.allclose(target, aim) or (np.allclose(target, 0.0) and heading < 1e-9)  # flies, or turns first
        else:
            assert decision.goal != key and key in planner._cooling


def test_after_a_loop_closure_each_step_walks_the_graph_for_a_bounded_number_of_keyframes():
    """After a loop closure every keyframe's check through the graph walks the whole graph
    afresh (1-2 ms each on a large map); a step does at most `fresh_graph_checks_per_step` of
    them, and the keyframes left over are checked on the next steps, none skipped for good."""
    m = LocalMap()
    prev: tuple[int, Pose2] | None = None
    ids = []
    for k in range(6):  # far apart: no two are neighbours, each keeps its frontiers
        pose = Pose2(12.0 * k, 0.0, 0.0)
        parent = None if prev is None else (prev[0], prev[1].between(pose))
        kf = m.add_keyframe(float(k), pose, scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)), parent)
        ids.append(kf.keyframe_id)
        prev = (kf.keyframe_id, pose)
    m.add_loop_closure(ids[0], ids[-1], Pose2(60.0, 0.0, 0.0))
    fresh: list[int] = []
    check = m.close_through_graph

    def counting(keyframe_id: int, since_id: int = 0) -> int:
        if since_id == 0:
            fresh.append(keyframe_id)
        return check(keyframe_id, since_id)

    m.close_through_graph = counting  # type: ignore[method-assign]
    planner = FrontierPlanner(PlannerParams(fresh_graph_checks_per_step=2))
    for step in range(3):
        planner._fresh_checks_left = planner.params.fresh_graph_checks_per_step  # as plan() does
        for k in ids:
            assert planner._has_live_targets(m, k, planner.params.fragment_size_m)  # unchecked ones still count as open
        assert len(fresh) == 2 * (step + 1)
    assert sorted(fresh) == sorted(ids)  # each walked once, over three steps


def test_a_leg_blocked_when_faced_is_planned_again_only_so_often_from_one_spot():
    """Two plans of one route leg, each blocked once faced (the sensor sees one way at a time),
    alternated for minutes on one spot. From one spot a leg is planned again `leg_replans` times,
    then counts as blocked; moved on, or towards another keyframe, it may be planned again."""
    planner = FrontierPlanner(PlannerParams(leg_replans=2, goal_reached_m=0.3))
    here = np.array([1.0, 2.0])
    assert planner._may_replan(7, 5, here)
    assert planner._may_replan(7, 5, here + 0.05)
    assert not planner._may_replan(7, 5, here)  # the third time from the same spot: blocked
    assert planner._may_replan(7, 5, here + 1.0)  # moved on
    assert planner._may_replan(7, 4, here + 1.0)  # another keyframe


def _closet_map() -> tuple[LocalMap, dict[str, int]]:
    """A room (x < 0) and a 1.35 m closet (x > 0) joined by a 0.8 m door in the wall x = 0
    (jambs at y = -0.5 and y = 0.3); keyframes taken on the way in, the last in the door's
    mouth looking out. Returns the map and its keyframe ids by name."""
    from sitl.depth_sensor import cast_rays

    walls = [
        ((-4.0, -2.0), (0.0, -2.0)),
        ((0.0, -2.0), (0.0, -0.5)),
        ((0.0, -0.675), (1.35, -0.675)),
        ((1.35, -0.675), (1.35, 0.675)),
        ((1.35, 0.675), (0.0, 0.675)),
        ((0.0, 0.3), (0.0, 2.0)),
        ((0.0, 2.0), (-4.0, 2.0)),
        ((-4.0, 2.0), (-4.0, -2.0)),
    ]
    walls_xy = np.array(walls, dtype=np.float64)
    bearings = np.linspace(-math.pi / 4, math.pi / 4, 160)
    m = LocalMap()
    ids: dict[str, int] = {}
    prev: tuple[int, Pose2] | None = None
    for name, pose in (
        ("outside", Pose2(-0.3, 0.4, -0.4)),  # behind the upper jamb, looking at the door
        ("doorway", Pose2(-0.5, -0.1, 0.0)),
        ("inside", Pose2(0.7, 0.0, math.pi)),
        ("mouth", Pose2(0.2, 0.0, math.pi)),  # 0.36 m from the upper jamb, looking out
    ):
        ranges = cast_rays(np.array([pose.x_m, pose.y_m]), bearings + pose.yaw_rad, walls_xy, 5.0)
        scan = DepthScan(0.0, bearings, np.where(np.isfinite(ranges), ranges, 5.0), 5.0)
        parent = None if prev is None else (prev[0], prev[1].between(pose))
        kf = m.add_keyframe(float(len(ids)), pose, scan_to_polygon(scan), parent)
        ids[name] = kf.keyframe_id
        prev = (kf.keyframe_id, pose)
    return m, ids


def test_a_leg_out_through_a_door_too_narrow_for_the_full_clearance_goes_through_the_door():
    """In a closet's doorway, the next route keyframe just behind a jamb: the straight leg grazes
    the jamb, and the free-space grid at the full clearance (0.4 m) finds a 0.8 m door closed.
    A leg needs the body radius and leg margin clear, so the grid at that clearance plans the
    way out through the door. (Apartment seed 6: the straight leg was seen blocked at every
    step, with no way round, and every frontier left was set aside from there at 0.785.)"""
    from companion.core.geometry import point_segment_distances

    m, ids = _closet_map()
    frame = ids["mouth"]
    planner = FrontierPlanner()
    world = Pose2(0.2, 0.0, math.pi)  # the mouth keyframe's pose in the world
    target = m.pose_in(frame, ids["outside"])
    wp = np.array([target.x_m, target.y_m])
    vehicle = Pose2(0.0, 0.0, math.atan2(wp[1], wp[0]))  # at the keyframe's origin, facing the leg
    live = world.inverse().apply(np.array([[0.0, y] for y in np.arange(0.3, 2.0, 0.05)]))  # the jamb's wall
    planner.plan(m, frame, vehicle, 100.0, live_obstacles_xy=live)
    view = m.view(frame)
    here = np.zeros(2)
    required = planner.params.clearance_m
    assert planner._leg_blocked(vehicle, here, wp, required)  # the straight leg grazes the jamb
    full = planner._reach(view, here)
    assert full is None or full.path_to(wp, snap=True) is None  # the door, at the full clearance
    points, fresh = planner._leg_points(m, frame, view, here, ids["outside"], wp, required)
    assert fresh and points.shape[0] >= 2
    path_world = world.apply(np.vstack((here, points)))
    legs = np.stack((path_world[:-1], path_world[1:]), axis=1)
    floor = planner.params.body_radius_m + planner.params.leg_margin_m
    jambs = np.array([[0.0, 0.3], [0.0, -0.5]])
    assert point_segment_distances(jambs, legs).min() >= floor - 0.03
    assert np.all(path_world[1:-1, 0] < 0.2)  # out through the door, not along the closet wall
    assert np.hypot(*(path_world[-1] - (-0.3, 0.4))) <= planner.params.grid.snap_m
    facing = Pose2(0.0, 0.0, math.atan2(points[0][1], points[0][0]))
    assert not planner._leg_blocked(facing, here, points[0], required)


def _all_surface(seen: bool, points_xy: np.ndarray, tol_m: float) -> np.ndarray:
    """A newest scan that sees every point as surface, or none."""
    return np.full(points_xy.shape[0], seen)


def test_frontiers_out_of_reach_from_their_origin_that_the_scan_sees_as_wall_are_closed_not_failed():
    """Flown back to a keyframe whose frontiers are out of reach from its origin: the vehicle
    first faces the way the keyframe looked (it then sees the whole polygon), and the frontiers
    the newest scan sees a wall right at are closed as walls, not counted as failed tries (set
    aside, such vertices by a corridor wall ended runs `unreachable_frontiers_left` at coverage
    1.000). Those it does not see as wall still count a failed try."""

    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    angles = np.linspace(0.0, 2.0 * math.pi, 90)
    boxed_in = 0.45 * np.column_stack((np.cos(angles), np.sin(angles)))  # returns all round: nothing in reach
    for seen_as_wall in (True, False):
        kf.kinds[:] = kf.polygon.kinds
        kf.version += 1
        planner = FrontierPlanner()
        planner.route = _Route([kf.keyframe_id], kf.keyframe_id)
        planner._arrived_at = kf.keyframe_id
        targets = planner._targets(m, kf.keyframe_id, planner.params.fragment_size_m)
        assert targets
        live = {"live_obstacles_xy": boxed_in, "live_surface": functools.partial(_all_surface, seen_as_wall)}
        planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 1.0), 100.0, **live)
        assert planner.route is not None and not planner.attempts  # it turns to look first
        assert np.all(kf.kinds[targets] == VertexKind.FRONTIER)
        planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.1, **live)
        if seen_as_wall:
            assert np.all(kf.kinds[targets] == VertexKind.OBSTACLE) and not planner.attempts
        else:
            assert np.all(kf.kinds[targets] == VertexKind.FRONTIER)
            assert {k.keyframe_id for k in planner.attempts} == {kf.keyframe_id}


def test_a_goal_on_a_path_at_a_legs_clearance_found_blocked_counts_a_failed_try():
    """A goal through the grid at a leg's clearance (the full clearance found no way) whose path
    the newest scan sees blocked counts a failed try, not only a cooldown: dropped and taken
    again in turn, such goals held a vehicle on one spot. Other goals found blocked cool down."""
    from companion.core.planner import _Candidate

    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    open_idx = targetable_indices(kf, 0.3)
    key = FrontierKey(kf.keyframe_id, int(open_idx[np.argmin(np.abs(kf.polygon.vertices_xy[open_idx, 1]))]))
    goal_xy = np.array([3.0, 0.0])
    jamb = np.array([[1.5, 0.1]])  # right on the path's first leg
    for eased in (True, False):
        planner = FrontierPlanner()
        planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0, live_obstacles_xy=jamb)
        candidate = _Candidate(key, goal_xy, 0.0, 0.0, path=goal_xy[None, :].copy(), eased=eased)
        planner._commit(m, kf.keyframe_id, candidate, np.zeros(2), 100.0)
        planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.1, live_obstacles_xy=jamb)
        assert key in planner._cooling
        assert planner.attempts.get(key, 0) == (1 if eased else 0)


def test_a_goal_whose_last_leg_is_blocked_this_near_is_looked_from_where_the_vehicle_is():
    """0.4 m short of a goal on a path at a leg's clearance, the newest scan sees its last leg
    pass a return too close: the vehicle looks from where it is (the goal moves there, no try is
    counted) rather than dropping it. Found blocked 0.42 m short, such a goal counted a failed
    try, was out of reach from its keyframe and set aside at coverage 1.000 (room seed 13).
    From 1 m short it is dropped and counts the try, as before."""
    from companion.core.planner import _Candidate

    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    open_idx = targetable_indices(kf, 0.3)
    key = FrontierKey(kf.keyframe_id, int(open_idx[np.argmin(np.abs(kf.polygon.vertices_xy[open_idx, 1]))]))
    goal_xy = np.array([3.0, 0.0])
    for start_x, kept in ((2.6, True), (2.0, False)):
        post = np.array([[start_x + 0.3, 0.2]])  # beside the last leg, 0.2 m from it
        planner = FrontierPlanner()
        candidate = _Candidate(key, goal_xy, 0.0, 0.0, path=goal_xy[None, :].copy(), eased=True)
        planner._commit(m, kf.keyframe_id, candidate, np.array([start_x, 0.0]), 100.0)
        planner.plan(m, kf.keyframe_id, Pose2(start_x, 0.0, 0.0), 100.1, live_obstacles_xy=post)
        assert (planner.goal is not None and planner.goal.key == key) is kept
        assert planner.attempts.get(key, 0) == (0 if kept else 1)
        if kept:
            assert planner.goal is not None and planner.goal.path is None
            assert np.allclose(planner.goal.local_xy, (start_x, 0.0))  # looked from here


def test_a_goal_found_blocked_again_from_the_same_spot_counts_a_failed_try():
    """The first time the newest scan sees a goal's path blocked, it only cools down; found
    blocked again from the same spot when taken after that, it counts a failed try, so a
    frontier only the sensor facing it sees blocked is set aside in the end: taken, dropped,
    and flown away from and back to every 10 s, one held lshape seed 1 (perfect odometry, no
    loop closures) for 700 s. Found blocked from elsewhere each time, it only cools down."""
    from companion.core.planner import _Candidate

    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    open_idx = targetable_indices(kf, 0.3)
    key = FrontierKey(kf.keyframe_id, int(open_idx[np.argmin(np.abs(kf.polygon.vertices_xy[open_idx, 1]))]))
    goal_xy = np.array([3.0, 0.0])
    jamb = np.array([[1.8, 0.1]])  # on the path's first leg from every start below

    def tries_when_dropped_from(xs: list[float]) -> tuple[list[int], FrontierPlanner]:
        planner = FrontierPlanner(PlannerParams(max_attempts=2, blocked_cooldown_s=5.0))
        tries = []
        for i, x in enumerate(xs):  # each after the last one's cooldown
            t = 100.0 + 10.0 * i
            candidate = _Candidate(key, goal_xy, 0.0, 0.0, path=goal_xy[None, :].copy())
            planner._commit(m, kf.keyframe_id, candidate, np.array([x, 0.0]), t)
            planner.plan(m, kf.keyframe_id, Pose2(x, 0.0, 0.0), t + 0.1, live_obstacles_xy=jamb)
            assert planner.goal is None or planner.goal.key != key
            tries.append(planner.attempts.get(key, 0))
        return tries, planner

    tries, planner = tries_when_dropped_from([0.0, 0.0, 0.0])
    assert tries == [0, 1, 2]
    assert key not in planner.set_aside  # not yet: one last try from its keyframe's origin
    planner._failed(key, 200.0)
    assert key in planner.set_aside
    tries, planner = tries_when_dropped_from([0.0, 0.5, 1.0])
    assert tries == [0, 0, 0]


def test_a_route_that_keeps_getting_shorter_is_progress_one_that_does_not_stalls():
    """Skipping ahead along a long corridor, the vehicle passes route keyframes without slowing
    at them, so none counts as reached: each shorter route to the same target is progress, and
    only ``route_timeout_s`` without any stalls the route (a failed try for its target)."""
    planner = FrontierPlanner(PlannerParams(route_timeout_s=30.0))
    route = _Route(list(range(70, 0, -1)), 1)
    assert not planner._route_stalled(route, 100.0)
    for k in range(1, 6):  # 100 s of flight, a few keyframes skipped every 20 s
        del route.keyframes[:5]
        assert not planner._route_stalled(route, 100.0 + 20.0 * k)
    assert not planner._route_stalled(route, 229.0)
    assert planner._route_stalled(route, 231.0)  # 31 s since the last keyframe was passed
    longer = _Route(list(range(60, 0, -1)), 1)  # found again from elsewhere: no shorter
    assert planner._route_stalled(longer, 231.0)
    assert not planner._route_stalled(_Route([5, 4], 4), 231.0)  # another target starts afresh


def test_a_goal_taken_on_the_way_restarts_the_routes_watchdog():
    """Flying a route, the vehicle found frontiers on the way and explored them for minutes. The
    next route to the same target is a fresh one: its first step must not find it stalled and
    count a failed try for the target's frontiers (three, and they were set aside)."""
    from companion.core.planner import _Candidate

    m, kf, key = _open_view_with_a_frontier_ahead()
    planner = FrontierPlanner(PlannerParams(route_timeout_s=30.0))
    assert not planner._route_stalled(_Route([9, 8, 7], 7), 100.0)
    planner._commit(m, kf.keyframe_id, _Candidate(key, np.array([3.0, 0.0]), 0.0, 0.0), np.zeros(2), 110.0)
    planner.goal = None  # explored until 140 s
    again = _Route([9, 8, 7], 7)  # the same target, as far as before
    assert not planner._route_stalled(again, 140.0)
    assert not planner._route_stalled(again, 169.0)
    assert planner._route_stalled(again, 171.0)  # no progress for 31 s of this route: stalled


def test_a_goal_off_the_heading_is_flown_to_while_its_path_stays_inside_the_sensors_view():
    """The only frontier lies straight ahead along x and the vehicle faces 0.5 rad to its left.
    With a 90-degree camera the path stays inside the view (the turn-first limit is the half
    field of view less its margin): the vehicle flies on, turning as it goes. With a 57-degree
    camera the same path lies outside the view less its margin: it stops and turns first."""
    narrow = np.linspace(-0.1, 0.1, 9)
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, narrow, np.full(9, 5.0), 5.0)))
    vehicle = Pose2(0.0, 0.0, 0.5)
    p = PlannerParams()
    for half_fov_rad, turns_first in ((math.pi / 4, False), (0.5, True)):
        assert (half_fov_rad - p.fov_edge_margin_rad < 0.5) == turns_first
        target = FrontierPlanner(p).plan(m, kf.keyframe_id, vehicle, 0.0, half_fov_rad=half_fov_rad).target
        moves_off = math.hypot(target.x_m, target.y_m) > 1.0
        assert moves_off != turns_first
        if turns_first:
            assert abs(target.yaw_rad) < 0.15  # it turns towards the goal ahead


def test_on_a_goals_last_metre_the_vehicle_turns_to_look_as_it_flies_in():
    """Within ``look_ahead_m`` of its goal, once facing the straight path to it (the sensor has
    seen that path), the vehicle turns to the goal's look while it flies in, and goes on flying
    in however far the turn takes its heading off the path. Farther out, or not yet facing the
    path, it flies (or turns first) facing the way it goes; so it does throughout with
    ``look_ahead_m`` 0."""

    def committed(params: PlannerParams) -> tuple[LocalMap, int, FrontierPlanner, Callable[..., tuple[float, ...]]]:
        m = LocalMap()
        no_sides = PolygonParams(side_frontier_spacing_m=0.0)
        scan = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
        kf_id = m.add_keyframe(0.0, Pose2(), scan_to_polygon(scan, no_sides)).keyframe_id
        planner = FrontierPlanner(params)
        planner.plan(m, kf_id, Pose2(), 0.0)
        goal = planner.goal
        assert goal is not None and math.hypot(*goal.local_xy) > 2.0
        goal.look_local_rad = math.atan2(goal.local_xy[1], goal.local_xy[0]) + 1.2  # the vertex lies off the way in
        stamp = [0.0]

        def target(back_m: float, yaw_off_rad: float) -> tuple[float, ...]:
            """For the vehicle ``back_m`` short of the goal on its path, heading ``yaw_off_rad``
            off the way in: the target's distance from the goal, its yaw's offset from the look
            and from the way in (radians), and whether the plan asks for a keyframe (0 or 1)."""
            gx, gy = goal.local_xy
            travel = math.atan2(gy, gx)
            x, y = gx - back_m * math.cos(travel), gy - back_m * math.sin(travel)
            stamp[0] += 0.1
            d = planner.plan(m, kf_id, Pose2(x, y, travel + yaw_off_rad), stamp[0])
            assert planner.goal is goal
            t = d.target
            off_look = abs(math.remainder(t.yaw_rad - goal.look_local_rad, math.tau))
            off_travel = abs(math.remainder(t.yaw_rad - travel, math.tau))
            return math.hypot(t.x_m - gx, t.y_m - gy), off_look, off_travel, float(d.want_keyframe)

        return m, kf_id, planner, target

    m, kf_id, planner, target = committed(PlannerParams())
    to_goal, _, off_travel, _ = target(1.5, 0.0)  # farther out: facing the way it flies
    assert to_goal == 0.0 and off_travel < 1e-9
    to_goal, _, off_travel, _ = target(0.8, 1.0)  # close, but facing away: turns to the path first
    assert to_goal > 0.7 and off_travel < 1e-9
    to_goal, off_look, _, _ = target(0.8, 0.0)  # close, facing the path: flies in, turning to look
    assert to_goal == 0.0 and off_look < 1e-9
    to_goal, off_look, _, _ = target(0.5, 0.9)  # half turned, the path off the view: flies on
    assert to_goal == 0.0 and off_look < 1e-9
    # A view taken turning sees the vertex and closes it: the vehicle still flies in, for the
    # view on arrival (it sees round the vertex); then the goal is done, with no settling.
    goal = planner.goal
    assert goal is not None
    m.close_frontiers(kf_id, np.array([goal.key.index]))
    to_goal, off_look, _, _ = target(0.35, 1.1)
    assert to_goal == 0.0 and off_look < 1e-9
    _, _, _, want_keyframe = target(0.0, 1.2)  # arrived, looking
    assert want_keyframe
    planner.plan(m, kf_id, Pose2(*goal.local_xy, goal.look_local_rad), 99.0)
    assert planner.goal is not goal

    _, _, _, target = committed(PlannerParams(look_ahead_m=0.0))
    to_goal, _, off_travel, _ = target(0.8, 0.0)
    assert to_goal == 0.0 and off_travel < 1e-9


@pytest.mark.parametrize("flown", [True, False])
def test_a_route_leg_seen_blocked_is_flown_back_the_way_the_vehicle_came(flown):
    """Keyframe B was taken 3 m north of A, out of its sight: the vehicle flew round the end of a
    wall between them (x < 1.5 m at y = 1.5 m). Flying back from B to A, the straight leg is seen
    blocked and B hangs off the graph by that edge alone: with no way round in view, every
    frontier beyond was set aside in turn while the vehicle hovered (office seed 8 without loop
    closures, coverage 0.83). The way flown is kept with the edge and flown back instead."""
    world_a, world_b = Pose2(0.0, 0.0, math.pi), Pose2(0.0, 3.0, 0.0)  # they look away from each other
    flown_world = np.array([[2.0, 0.5], [2.0, 1.5], [2.0, 2.5]])
    m = LocalMap()
    open_scan = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
    a = m.add_keyframe(0.0, world_a, scan_to_polygon(open_scan))
    b_in_a = world_a.between(world_b)
    way = world_a.inverse().apply(flown_world) if flown else None
    b = m.add_keyframe(1.0, world_b, scan_to_polygon(open_scan), (a.keyframe_id, b_in_a), way)
    b.kinds[b.kinds == VertexKind.FRONTIER] = VertexKind.FREE  # nothing left to explore from B
    b.version += 1
    wall = world_b.inverse().apply(np.array([[x, 1.5] for x in np.arange(-3.0, 1.5, 0.05)]))
    planner = FrontierPlanner()
    planner.route = _Route([a.keyframe_id], a.keyframe_id)
    vehicle = Pose2(0.0, 0.0, -math.pi / 2)  # at B, facing A
    decision = planner.plan(m, b.keyframe_id, vehicle, 100.0, live_obstacles_xy=wall)
    assert decision.mode is Mode.BACKTRACKING
    if flown:
        back = world_b.inverse().apply(flown_world[::-1])
        assert planner._leg is not None and planner._leg.flown
        assert np.allclose(planner._leg.points[:-1], back)
        assert math.isclose(decision.target.yaw_rad, math.atan2(back[0, 1], back[0, 0]), abs_tol=1e-9)
        assert not planner.attempts and planner.route is not None
    else:
        assert {k.keyframe_id for k in planner.attempts} == {a.keyframe_id}  # a failed try for A


def test_a_frontier_that_used_up_its_tries_is_tried_once_more_from_its_own_keyframes_origin():
    """There its vertex lies where its own scan put it; placed in any other (drifted) frame it
    may lie in a wall: every later view of corridor seed 5 put a range-end vertex 0.3-0.5 m
    inside the corridor's wall, took it from there, dropped it twice and set it aside at
    coverage 1.000. So its last try is from its origin (only), and only a failure there sets it
    aside. A frontier with tries left is taken from anywhere."""
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    keys = [FrontierKey(kf.keyframe_id, int(i)) for i in targetable_indices(kf, PlannerParams().min_frontier_size_m)]
    assert keys
    away = Pose2(1.5, 0.0, 0.0)  # inside the keyframe's view, well off its origin

    planner = FrontierPlanner(PlannerParams(max_attempts=2))
    for k in keys:
        planner._failed(k, 50.0)  # one try left
    from_away = planner.plan(m, kf.keyframe_id, away, 100.0)
    assert from_away.mode is Mode.EXPLORING and from_away.goal in keys

    planner = FrontierPlanner(PlannerParams(max_attempts=2))
    for k in keys:
        planner._failed(k, 50.0)
        planner._failed(k, 60.0)  # tries used up elsewhere
    assert not planner.set_aside
    from_away = planner.plan(m, kf.keyframe_id, away, 100.0)
    assert from_away.mode is Mode.BACKTRACKING and planner.route is not None
    assert planner.route.keyframes == [kf.keyframe_id]  # back to its origin for it
    at_origin = planner.plan(m, kf.keyframe_id, Pose2(0.0, 0.0, 0.0), 101.0)
    assert at_origin.mode is Mode.EXPLORING and at_origin.goal in keys
    planner._failed(at_origin.goal, 110.0)  # and failed there too: set aside
    assert at_origin.goal in planner.set_aside


def test_a_vehicle_braking_past_its_routes_end_backs_up_to_it_facing_the_keyframes_way():
    """The route's end is the keyframe just taken, and the vehicle brakes past its origin. Within
    the waypoint radius it backs up there facing the way that keyframe looked, as it will once
    there: turned round to face a hop that short, it turned back on arrival (5 s on one spot in
    lshape seed 1). Farther off it turns to face its way first, as on any leg."""
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)))
    keys = [FrontierKey(kf.keyframe_id, int(i)) for i in targetable_indices(kf, PlannerParams().min_frontier_size_m)]
    p = PlannerParams(max_attempts=2)
    for past_m, backs_up in ((0.4, True), (0.8, False)):
        assert (past_m <= p.waypoint_reached_m) == backs_up
        planner = FrontierPlanner(p)
        for k in keys:  # tries used up elsewhere: from its origin only, so the vehicle goes there
            planner._failed(k, 50.0)
            planner._failed(k, 60.0)
        vehicle = Pose2(past_m, 0.0, 0.0)
        decision = planner.plan(m, kf.keyframe_id, vehicle, 100.0, velocity_xy=(1.0, 0.0))
        assert decision.mode is Mode.BACKTRACKING and planner.route is not None
        assert planner.route.keyframes == [kf.keyframe_id]
        t = decision.target
        if backs_up:
            assert math.hypot(t.x_m, t.y_m) < 1e-9 and abs(t.yaw_rad) < 1e-9
        else:
            assert math.isclose(abs(t.yaw_rad), math.pi, abs_tol=1e-6)  # turns round to face its way


def test_a_frontier_where_the_vehicle_already_flew_and_looked_is_closed_not_flown_to_again():
    """Without loop closures, a route restarted from one spot every 16 s: each new view there
    offered a frontier vertex at the place the vehicle had just flown to and looked at, whose
    views held it too shallowly to close it, and the vehicle went again, until the time limit
    (room seed 8 at coverage 0.91). A vertex that close to a place looked at, placed along the
    pose graph, and facing the way it was looked at, is closed as looked at; one facing another
    way there looks into other space (a door's frontier seen from a room beside it)."""
    scan = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)

    def two_views() -> tuple[LocalMap, int, int]:
        m = LocalMap()
        a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(scan))
        step = Pose2(0.5, 0.0, 0.0)
        b = m.add_keyframe(1.0, step, scan_to_polygon(scan), parent=(a.keyframe_id, step))
        return m, a.keyframe_id, b.keyframe_id

    m, a, b = two_views()
    first = FrontierPlanner(PlannerParams(looked_radius_m=0.5)).plan(m, b, Pose2(0.0, 0.0, 0.0), 100.0)
    assert first.goal is not None
    owner = m.keyframes[first.goal.keyframe_id]
    placed = m.pose_in(a, owner.keyframe_id)
    vertex_in_a = placed.apply(owner.polygon.vertices_xy[[first.goal.index]])[0]
    outward = owner.polygon.outward_xy[first.goal.index]
    facing = math.atan2(outward[1], outward[0]) + placed.yaw_rad  # looked at it along its normal

    for radius, look, closed in ((0.5, facing, True), (0.0, facing, False), (0.5, facing + math.pi, False)):
        m, a, b = two_views()
        planner = FrontierPlanner(PlannerParams(looked_radius_m=radius))
        planner._looked = {a: [(float(vertex_in_a[0]), float(vertex_in_a[1]), look)]}  # looked at, from a's view
        again = planner.plan(m, b, Pose2(0.0, 0.0, 0.0), 100.0)
        assert (again.goal != first.goal) is closed
        assert bool(m.keyframes[first.goal.keyframe_id].kinds[first.goal.index] != VertexKind.FRONTIER) is closed


def test_a_goal_vertex_hidden_behind_the_wall_faced_on_arrival_is_a_failed_try_not_looked_at():
    """Arrived at a goal and settled, the vehicle faced a wall with the goal's vertex 0.7 m
    behind it: drift had placed a view seen through a door in the room next door. Closed as
    looked at, that room was never entered (lshape seed 2, in a variant, `complete` at 0.96).
    Hidden behind the scanned surface, the vertex stays open, the goal counts a failed try, and
    its place is not remembered as looked at (it closed the frontiers truly there, apartment
    seed 9 in a variant); not hidden, it is closed as looked at, and so is that frontier again."""
    scan = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)

    def settle(hidden: bool) -> tuple[FrontierPlanner, LocalMap, FrontierKey]:
        m = LocalMap()
        a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(scan)).keyframe_id
        planner = FrontierPlanner()
        assert planner.plan(m, a, Pose2(0.0, 0.0, 0.0), 100.0).goal is not None
        goal = planner.goal
        assert goal is not None
        at = Pose2(goal.local_xy[0], goal.local_xy[1], goal.look_local_rad)

        def live_hidden(points_xy: np.ndarray, depth_m: float) -> np.ndarray:
            return np.full(points_xy.shape[0], hidden)

        for t in (100.1, 100.2 + planner.params.settle_s):
            planner.plan(m, a, at, t, live_hidden=live_hidden)
        return planner, m, goal.key

    def seen_again(planner: FrontierPlanner, m: LocalMap, key: FrontierKey) -> bool:
        """Is the same frontier, in a new view from the same spot, closed as looked at?"""
        again = m.add_keyframe(1.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(scan), (key.keyframe_id, Pose2.identity()))
        assert again.kinds[key.index] == VertexKind.FRONTIER
        planner.plan(m, again.keyframe_id, Pose2(0.0, 0.0, 0.0), 200.0)
        return bool(again.kinds[key.index] != VertexKind.FRONTIER)

    planner, m, key = settle(hidden=True)
    assert m.keyframes[key.keyframe_id].kinds[key.index] == VertexKind.FRONTIER
    assert planner.attempts.get(key) == 1
    assert planner.goal is None or planner.goal.key != key  # dropped (cooling), another goal taken
    # Nothing was looked at there: a frontier at that place (in truth beyond the wall) stays open.
    assert not seen_again(planner, m, key)
    planner, m, key = settle(hidden=False)
    assert m.keyframes[key.keyframe_id].kinds[key.index] != VertexKind.FRONTIER
    assert planner.attempts.get(key) is None
    assert seen_again(planner, m, key)


def test_a_frontier_facing_only_a_sliver_is_closed_when_weighed_not_flown_to():
    """A's only frontier vertex, at (2, 0), faces +x; B saw a wall ``gap`` beyond it (from behind)
    and the space above A. At 0.25 m the unseen space there is a sliver: the planner closes the
    vertex and has nothing to fly to. At 0.8 m it is the goal. Slivers are judged only in a step
    that finds the map as the last step left it (a new keyframe makes a step dear enough): the
    first step takes the vertex unjudged, the next one judges it."""
    from test_local_map import sliver_map

    goals = []
    for gap in (0.25, 0.8):
        m, a_id = sliver_map(2.0, gap)
        a = m.keyframes[a_id]
        planner = FrontierPlanner()
        first = planner.plan(m, a_id, Pose2(0.0, 0.0, 0.0), 0.0)
        assert first.goal == FrontierKey(0, 2) and a.kinds[2] == VertexKind.FRONTIER
        goals.append(planner.plan(m, a_id, Pose2(0.0, 0.0, 0.0), 0.1).goal)
        assert a.kinds[2] == (VertexKind.FREE if gap < 0.4 else VertexKind.FRONTIER)
    assert goals == [None, FrontierKey(0, 2)]


@pytest.mark.parametrize("stalled", [False, True])
def test_a_route_leg_the_vehicle_stood_still_on_is_taken_as_blocked(stalled):
    """The straight leg from B back to A is clear to the newest scan, but the vehicle stood still
    on it (``note_stall``: held by something the plan does not see): that plan takes the leg as
    blocked and flies back the way the vehicle came, as when the sensor sees it so. Only that
    plan: the note is not carried to the next."""
    world_a, world_b = Pose2(0.0, 0.0, math.pi), Pose2(0.0, 3.0, 0.0)
    flown_world = np.array([[2.0, 0.5], [2.0, 1.5], [2.0, 2.5]])
    m = LocalMap()
    open_scan = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
    a = m.add_keyframe(0.0, world_a, scan_to_polygon(open_scan))
    way = world_a.inverse().apply(flown_world)
    b = m.add_keyframe(1.0, world_b, scan_to_polygon(open_scan), (a.keyframe_id, world_a.between(world_b)), way)
    b.kinds[b.kinds == VertexKind.FRONTIER] = VertexKind.FREE
    b.version += 1
    planner = FrontierPlanner()
    planner.route = _Route([a.keyframe_id], a.keyframe_id)
    vehicle = Pose2(0.0, 0.0, -math.pi / 2)  # at B, facing A
    if stalled:
        planner.note_stall()
    decision = planner.plan(m, b.keyframe_id, vehicle, 100.0, live_obstacles_xy=np.zeros((0, 2)))
    assert decision.mode is Mode.BACKTRACKING
    a_in_b = world_b.inverse().apply(np.array([[0.0, 0.0]]))[0]
    if stalled:
        back = world_b.inverse().apply(flown_world[::-1])
        assert planner._leg is not None and planner._leg.flown
        assert np.allclose(planner._leg.points[:-1], back)
    else:
        assert planner._leg is not None and not planner._leg.flown
        assert np.allclose(planner._leg.points[-1], a_in_b)
    assert not planner._stalled and not planner._stall_noted  # used up by this plan


@pytest.mark.parametrize("checked", [2, 200])
def test_a_frontier_ranked_low_by_heading_is_taken_straight_when_the_best_have_no_path(checked):
    """A wall 2 m ahead with a gap too narrow to fly: the frontiers seen through it rank best
    by heading, and none has a path. A frontier off to the side ranks lower and has a straight
    path: the first choice takes it when it is among the candidates checked, instead of leaving
    the choice to a route back (corridor seed 6: at the mouth, the corners' goals ranked 25th
    and lower, and the vehicle went down the corridor and came back for them)."""
    ranges = 2.0 / np.cos(BEARINGS)  # a wall across the way, 2 m ahead
    ranges[(BEARINGS > 0.25) & (BEARINGS < 0.40)] = 5.0  # seen through a 0.3 m gap
    ranges[BEARINGS < -0.45] = 5.0  # the wall ends on the right: open beyond
    polygon = scan_to_polygon(
        DepthScan(0.0, BEARINGS, ranges, 5.0),
        PolygonParams(side_frontier_spacing_m=0.0, occlusion_frontier_spacing_m=0.0),
    )
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), polygon)
    m.close_frontiers(kf.keyframe_id, np.flatnonzero(np.hypot(*polygon.vertices_xy.T) < 3.0))  # the jambs
    params = PlannerParams(max_candidates_checked=checked)
    planner = FrontierPlanner(params)
    vehicle = Pose2(0.0, 0.0, 0.0)
    view = m.view(kf.keyframe_id)
    here = np.zeros(2)
    chosen = planner._select_local(m, kf.keyframe_id, view, vehicle, here, planner.params.clearance_m)
    if checked == 2:
        assert chosen is None  # the two best lie through the gap: no straight path, no free-space one
    else:
        assert chosen is not None and chosen.path is None  # straight
        vertex = kf.polygon.vertices_xy[chosen.key.index]
        assert math.atan2(vertex[1], vertex[0]) < -0.45  # the frontier beyond the wall's end


def test_keyframes_tried_in_vain_one_after_another_wait_behind_the_others():
    """Hovering at a door, the vehicle took keyframe after keyframe on one spot, each holding the
    same frontier out of reach through it. The route went to each in turn, found it out of reach
    from its origin (one try per cooldown), and went back to the one tried before: apartment
    seed 1 hovered so for 30 s. Every keyframe tried in vain waits behind the keyframes not
    tried, so the route goes on to C's open frontiers 20 m away."""
    ranges = 1.0 / np.cos(BEARINGS)  # a wall 1 m ahead, with a crack seen through to 5 m
    ranges[(BEARINGS > 0.25) & (BEARINGS < 0.3)] = 5.0
    door = scan_to_polygon(
        DepthScan(0.0, BEARINGS, ranges, 5.0),
        PolygonParams(side_frontier_spacing_m=0.0, occlusion_frontier_spacing_m=0.0),
    )
    m = LocalMap()
    a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), door)
    b = m.add_keyframe(1.0, Pose2(0.05, 0.0, 0.0), door, (a.keyframe_id, Pose2(0.05, 0.0, 0.0)))
    scan_5m = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
    c = m.add_keyframe(2.0, Pose2(20.05, 0.0, 0.0), scan_to_polygon(scan_5m), (b.keyframe_id, Pose2(20.0, 0.0, 0.0)))
    for kf in (a, b):  # only the frontier beyond the crack is left open
        idx = np.flatnonzero(kf.kinds == VertexKind.FRONTIER)
        m.close_frontiers(kf.keyframe_id, idx[np.hypot(*kf.polygon.vertices_xy[idx].T) < 3.0])
    params = dataclasses.replace(PlannerParams(), approach_gain_m=10.0)  # no step nearer the crack
    assert all(FrontierPlanner(params)._targets(m, kf.keyframe_id, params.min_frontier_size_m) for kf in (a, b, c))
    planner = FrontierPlanner(params)
    frame, targets = a.keyframe_id, []
    for step in range(12):
        here = Pose2(0.0, 0.0, 0.0) if frame == a.keyframe_id else Pose2(-0.05, 0.0, 0.0)
        decision = planner.plan(m, frame, here, 100.0 + 0.1 * step)
        frame = decision.relocalize_to if decision.relocalize_to is not None else frame
        if planner.route is not None:
            targets.append(planner.route.target_keyframe)
    # A was tried (and its route ended) within the first step; B the next; then C, not A again.
    assert sorted(k.keyframe_id for k in planner.attempts) == [a.keyframe_id, b.keyframe_id]
    assert targets[0] == b.keyframe_id and set(targets[1:]) == {c.keyframe_id}


@pytest.mark.parametrize("scene", ["corridor", "corridor_past_a_jamb", "missed_returns", "corner"])
def test_a_far_range_limit_fragment_counts_only_in_an_opening_between_parallel_walls(scene):
    """Once nothing nearer is left, a range-limit fragment is flown to from anywhere only if it
    lies in an opening: walls by its bracketing vertices at least 0.6 m apart and about parallel
    (a corridor seen end-on, a door). Returns missed on one wall (both on the same wall) and a
    room's far corner (walls meeting) are remnants, not the way on. Here the range arc is closed
    as walls but for two vertices in its middle (as other views' walls close it): a fragment
    every time, so only the opening test tells them apart. Any wall by each end counts, not
    only the nearest: past a door's jamb the jamb's face is nearer than the corridor's wall."""
    n = 181
    bearings = np.linspace(-math.pi / 4, math.pi / 4, n)
    sin = np.maximum(np.abs(np.sin(bearings)), 1e-9)
    if scene == "corridor":  # side walls 0.6 m each side, seen end-on: open past 5 m in the middle
        ranges = 0.6 / sin
    elif scene == "corridor_past_a_jamb":  # and a jamb 0.25 m deep on the right at x = 4.85
        on_jamb = (bearings < 0.0) & (4.85 * np.tan(-bearings) >= 0.35) & (4.85 * np.tan(-bearings) <= 0.6)
        ranges = np.where(on_jamb, 4.85 / np.cos(bearings), 0.6 / sin)
    elif scene == "missed_returns":  # a wall across at 4.9 m, a dark patch on it gives no return
        ranges = 4.9 / np.cos(bearings)
        ranges[np.abs(bearings) < 0.06] = 9.0
    else:  # walls at x = 4.5 and y = 2.5 meet 5.15 m away: out of range round the corner
        ranges = np.minimum(4.5 / np.cos(bearings), np.where(bearings > 0, 2.5 / sin, 9.0))
    polygon = scan_to_polygon(DepthScan(0.0, bearings, np.minimum(ranges, 9.0), 5.0))
    m = LocalMap()
    kf = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), polygon)
    rl = np.flatnonzero((kf.kinds == VertexKind.FRONTIER) & kf.polygon.at_range_limit)
    if scene == "corner":  # the arc round the corner ahead-left (not the one past x = 4.5 on the right)
        rl = rl[kf.polygon.vertices_xy[rl, 1] > 0.0]
    assert rl.size >= 2
    keep = rl[rl.size // 2 - 1 : rl.size // 2 + 1]
    idx = np.flatnonzero(kf.kinds == VertexKind.FRONTIER)
    m.close_frontiers(kf.keyframe_id, np.setdiff1d(idx, keep), VertexKind.OBSTACLE)
    params = PlannerParams()
    size = run_sizes_m(kf.kinds, kf.polygon.vertices_xy)[keep[0]]
    assert params.fragment_size_m <= size < params.min_frontier_size_m
    planner = FrontierPlanner(params)
    found = planner._targets(m, kf.keyframe_id, params.fragment_size_m, range_limit_only=True)
    opening = scene.startswith("corridor")
    assert found == (keep.tolist() if opening else [])
    # From a keyframe 20 m back along the graph, nothing else open: flown to only in the corridor.
    far_id = m.add_keyframe(
        1.0, Pose2(-20.0, 0.0, 0.0), _walled_in_polygon(), (kf.keyframe_id, Pose2(-20.0, 0.0, 0.0))
    ).keyframe_id
    far = FrontierPlanner(params)
    decision = far.plan(m, far_id, Pose2(0.0, 0.0, 0.0), 0.0)
    if opening:
        assert decision.mode is Mode.BACKTRACKING and far.route is not None
        assert far.route.target_keyframe == kf.keyframe_id
        off = dataclasses.replace(params, far_range_limit_fragments=False)
        assert FrontierPlanner(off).plan(m, far_id, Pose2(0.0, 0.0, 0.0), 0.0).mode is Mode.COMPLETE
    else:
        assert decision.mode is Mode.COMPLETE


def _walled_in_polygon() -> FovPolygon:
    """A view of a wall 1 m ahead all across: no frontier run in it worth a flight."""
    return scan_to_polygon(DepthScan(0.0, BEARINGS, 1.0 / np.cos(BEARINGS), 5.0))


@pytest.mark.parametrize("sight_trim_m", [0.2, 0.0])
def test_a_goal_found_by_a_detour_is_one_from_which_the_vehicle_sees_its_vertex(sight_trim_m):
    """At A's origin its frontier ahead (5 m) is reached only round a pillar B saw 2 m ahead, by a
    path through known free space. C saw a wall across 0.6 m short of the vertex: its plain goals
    (1 m, 0.6 m and 1.5 m back along its normal) lie behind that wall, where the vehicle would
    look at the wall (lshape seed 7 flew round through the next room to such a goal). The goal
    taken is one shifted sideways, whose line of sight passes the wall's end; with the check off
    (``sight_trim_m`` 0), the plain one."""
    m = LocalMap()
    open_arc = DepthScan(0.0, BEARINGS, np.full(64, 5.0), 5.0)
    a = m.add_keyframe(0.0, Pose2(0.0, 0.0, 0.0), scan_to_polygon(open_arc))
    ranges = np.full(64, 5.0)
    ranges[np.abs(BEARINGS) < 0.04] = 2.0
    b = m.add_keyframe(1.0, Pose2(), scan_to_polygon(DepthScan(0.0, BEARINGS, ranges, 5.0)), (a.keyframe_id, Pose2()))
    c_pose = Pose2(4.7, 0.0, math.pi)  # looking back at a wall across x = 4.4, |y| <= 0.3
    c = m.add_keyframe(
        2.0, c_pose, scan_to_polygon(DepthScan(0.0, BEARINGS, 0.3 / np.cos(BEARINGS), 5.0)), (b.keyframe_id, c_pose)
    )
    for kf in (b, c):
        m.close_frontiers(kf.keyframe_id, np.flatnonzero(kf.kinds == VertexKind.FRONTIER))
    idx = np.flatnonzero(a.kinds == VertexKind.FRONTIER)
    m.close_frontiers(a.keyframe_id, idx[np.abs(a.polygon.vertices_xy[idx, 1]) > 0.3])
    assert np.count_nonzero(a.kinds == VertexKind.FRONTIER) == 2  # (5, -0.19) and (5, 0.19)
    wall = shapely.LineString([(4.4, -0.3), (4.4, 0.3)])

    class RoundThePillar(FrontierPlanner):
        def _reach(self, view: object, here: np.ndarray, clearance_m: float | None = None):  # type: ignore[override]
            class Reach:
                def path_to(self, goal_xy: np.ndarray, snap: bool = False) -> np.ndarray:
                    return np.array([[2.0, 1.0], goal_xy])

            return Reach()

    planner = RoundThePillar(PlannerParams(sight_trim_m=sight_trim_m))
    planner.route = _Route([a.keyframe_id], a.keyframe_id)
    planner._arrived_at = a.keyframe_id
    decision = planner.plan(m, a.keyframe_id, Pose2(0.0, 0.0, 0.0), 100.0)
    assert decision.mode is Mode.EXPLORING and planner.goal is not None and planner.goal.path is not None
    goal, vertex = planner.goal.local_xy, a.polygon.vertices_xy[planner.goal.key.index]
    crosses = shapely.LineString([goal, vertex - 0.2 * (vertex - goal) / np.hypot(*(vertex - goal))]).intersects(wall)
    assert crosses == (sight_trim_m == 0.0)
