"""Rapid frontier selection on the local-polygon map (thesis 2.9; Cieslewski et al. 2017).

Each step, in the frame of the current keyframe:

1. Keep the committed goal while its frontier is open and the straight path to it is accessible.
2. Otherwise pick, among the open frontiers of the current neighbourhood (the current view and
   the views that overlap it), the one needing the least change of heading, with distance as a
   small tie-break, whose goal point passes the accessibility check (2.9.2).
3. When none is accessible, fall back to the classical method (2.9.3): a breadth-first search along
   the pose graph to the nearest keyframe with open frontiers, flown back through the keyframes on
   that path as waypoints, each expressed relative to the current keyframe.

A goal point stands off from its frontier vertex into known free space: first on the frontier's
normal (the thesis's "normal point"), else back along the ray that observed it. Frontiers out of
reach even from their own keyframe's origin are approached (as near as the known free space leads,
for a new view there). Frontiers that stay open after ``max_attempts`` visits, or stay out of reach,
and then after one last try from their own keyframe's origin, are set aside so exploration always
ends.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.errors import GraphError
from companion.core.fov_polygon import KIND_FRONTIER, VertexKind
from companion.core.free_space_grid import FreeSpaceGrid, GridParams, Reach
from companion.core.frontiers import FrontierKey, run_brackets, targetable_indices, walled_runs
from companion.core.geometry import FloatArray, Pose2, apply_grouped, point_segment_distances, wrap_angle, wrap_angles
from companion.core.local_map import LocalMap, LocalView


class Mode(Enum):
    EXPLORING = "exploring"  # flying to a frontier of the current neighbourhood
    BACKTRACKING = "backtracking"  # flying back along the pose graph
    COMPLETE = "complete"  # no open, reachable frontier is left


@dataclass(frozen=True, slots=True)
class PlannerParams:
    """Tuning of the frontier planner; distances in metres, angles in radians, times in seconds."""

    body_radius_m: float = 0.25
    clearance_margin_m: float = 0.15
    standoff_m: float = 1.0
    # A run of open frontier shorter than this is a fragment, not worth a flight while a longer
    # run is left (the stale vertices of thesis 3.5.4). 0.6 m, session 50 (0.3 before): after
    # coverage 0.99, room seed 10 and cave seed 8 flew 58 and 49 s to runs of 0.4-1.1 m (a view's
    # range-limit corner by a wall, a vertex on its field of view's side) whose space views 17-18
    # hops along had seen, placed 0.4 m off, past what the drift margin lets close.
    min_frontier_size_m: float = 0.6
    # With no longer run left to fly to, fragments down to ``fragment_size_m`` whose keyframe lies
    # within ``fragment_reach_m`` are, before exploration ends: a fragment may be the way on. Never
    # flown to, runs under 0.8 m ended spiral seeds 3 and 4 `complete` at coverage 0.13, the
    # corridor's way on past its first corner a shadow edge of 0.65-0.78 m a few keyframes back.
    # Not from farther: routed back to from anywhere, the fragments left along the way took 3.4x
    # the time after coverage 0.99.
    fragment_size_m: float = 0.3
    fragment_reach_m: float = 4.0
    fragment_reach_hops: int = 40  # a longer chain of the graph is no measure of nearness
    # And with none of those left, range-limit fragments in an opening, from anywhere: no return
    # on their rays, so free space goes on beyond them. A 1.15 m corridor seen end-on from 5 m
    # kept one open vertex of its range arc (the others closed on its walls as other views
    # placed them), a run of 0.37 m and the only way to three rooms: apartment seed 3 (in a
    # variant) ended `complete` at coverage 0.78, 5.5 m from it. An opening: the run lies
    # between two vertices closed as walls, and the walls they lie by (within
    # ``opening_wall_m``, as views within ``fragment_reach_hops`` place them) are about
    # parallel (``opening_parallel_sin``) and at least ``min_frontier_size_m`` apart across
    # their lines: a corridor seen end-on; not a gap in one wall (returns missed on a wall at
    # the range limit), nor a room's far corner. Flown to from anywhere, every range-limit
    # fragment cost +7.4 % (those between walls +4.3 %): they are mostly such remnants, by the
    # building's outer wall or in corners.
    far_range_limit_fragments: bool = True
    opening_wall_m: float = 0.5
    opening_parallel_sin: float = 0.5  # the sine of the angle between the two walls, at most
    # The best this many candidates by score are checked for a straight path, then for a path
    # through free space; a route back only when none has either. 48 (24 before session 43): at
    # a corridor's mouth or a door the 24 best by heading often all lay past a jamb, and the
    # planner flew a free-space path or a route back while a frontier beside it, ranked lower,
    # had a straight path. Seeds 1-10: -2.0 % time; 96 was no better (docs/benchmarks.md).
    max_candidates_checked: int = 48
    # A goal's score: its change of heading plus this per metre to it (rapid selection's "least
    # change of heading", with distance as the tie-break that keeps the tour short). 0.2 in
    # session 23 (0.08 before): on 21 maps it flew shorter paths and ended sooner.
    distance_weight_rad_per_m: float = 0.2
    goal_reached_m: float = 0.3
    near_goal_m: float = 0.5  # a goal whose path's last leg is found blocked this near is looked from there
    same_view_rad: float = 0.5  # a goal at a keyframe's origin turned less than this repeats its view
    waypoint_reached_m: float = 0.5
    look_reached_rad: float = 0.3
    # On a goal's last metre, once the vehicle faces its straight path (so the sensor has seen
    # it), it turns to look at the frontier as it flies in, not after it stops: it arrives
    # looking. Turning on the spot at each goal was an eighth of the flight time on a 27-room
    # building (session 46). 0 turns only on arrival.
    look_ahead_m: float = 1.0
    # After arriving at a goal: how long to wait before a vertex still open is closed as looked
    # at (with its neighbours). A vertex the view on arrival closes is closed the next step; one
    # still open after that stayed open to the end of a 1 s wait (65 goals on a generated
    # building), so most of the wait bought nothing. 0.3 s since session 48 (1 s before): alone
    # -2.3 % and -3.3 % time on the shipped maps, seeds 1-5 and 6-10; held back in session 47
    # when its trajectories met a collision by the lead's remembered returns, until their berth
    # grew with their drift (companion.core.obstacle_memory). Session 20 had tried it and gone
    # back when lshape seed 11 ended at coverage 0.961; it now ends at 1.000 (lshape and
    # apartment, seeds 11-20, all `complete`). Without loop closures 1 s (companion.app.planner_params).
    settle_s: float = 0.3
    max_attempts: int = 2
    cruise_speed_mps: float = 1.5
    goal_timeout_min_s: float = 10.0
    # A goal farther off the heading (or, moving fast, off the motion) than this is turned to
    # (braked for) before the vehicle moves on: the sensor must see the path it flies. At most
    # the sensor's half field of view less ``fov_edge_margin_rad`` (the explorer passes it from
    # the scans): 0.6 rad keeps a path 10 degrees inside a 90-degree camera's view. Against
    # 0.35 rad, it cut the exploration time 7 % on 12 maps (session 23, seeds 1-3).
    turn_first_rad: float = 0.6
    fov_edge_margin_rad: float = 0.15
    shortcut_hops: int = 6
    leg_margin_m: float = 0.05
    route_timeout_s: float = 30.0  # backtracking without reaching a waypoint for this long fails the target
    side_shift_m: float = 0.5  # sideways goal shift tried from a keyframe's origin
    # A goal reached by a path through known free space (not straight) is taken only where the
    # vehicle would see its vertex: the line between them, short of the vertex by
    # ``sight_trim_m``, crosses no wall in view. A doorway vertex's normal point lay 1.1 m back,
    # across the wall between two rooms; the path went round through the other room's door, the
    # vehicle looked at the wall, flew back to the keyframe and took it again (lshape seed 7:
    # 30 s). 0 turns it off.
    sight_trim_m: float = 0.2
    approach_gain_m: float = 1.0  # an approach must end at least this much nearer its frontier
    # A route leg the newest scan sees blocked is flown round through the scan's own free space
    # (aims this far off the leg's line, this long, each at least the gain nearer the waypoint)
    # before it counts as blocked.
    sidestep_max_deg: float = 40.0
    sidestep_step_deg: float = 10.0
    sidestep_lengths_m: tuple[float, ...] = (0.5, 0.8, 1.2)
    sidestep_gain_m: float = 0.3
    # A leg of a goal's free-space path the scan sees so is flown round the same way rather than
    # dropping the goal (session 46; off without loop closures, see companion.app.planner_params).
    sidestep_goal_legs: bool = True
    stale_radius_m: float = 1.0  # looked at and still open: set aside this close around it too
    # A goal vertex the newest scan sees this far behind a surface, once arrived, was not looked
    # at (it lies beyond a wall: placed there by drift); closed as looked at, a room was lost.
    hidden_depth_m: float = 0.3
    # Checking a keyframe's frontiers through the graph after a loop closure walks the whole graph
    # (1-4 ms on a map of 300-450 keyframes), and one step could ask for several: at most this many
    # per step; the others are checked on the next steps (until then they count as open).
    fresh_graph_checks_per_step: int = 2
    # and at most this many frontier vertices judged for slivers (about 0.5-1 ms a call)
    sliver_checks_per_step: int = 2
    grid: GridParams = field(default_factory=GridParams)  # paths where a straight line is blocked
    goal_clearance_m: float = 0.3  # where a straight path ends keeps this clear, however close the start
    blocked_cooldown_s: float = 5.0  # a goal dropped as blocked is not taken again for this long
    # A route leg found blocked once faced is planned again with the newest scan this many times
    # from one spot, then counts as blocked: two plans, each blocked once faced (the sensor sees
    # one way at a time), alternated for minutes.
    leg_replans: int = 2
    corner_reached_m: float = 0.25  # a path's corner counts as passed this close (slow, no overshoot)
    corner_speed_mps: float = 0.5  # and a waypoint as reached only this slow: a sharp turn after it
    # must not carry the vehicle's momentum sideways into a wall
    # A goal candidate the newest scan sees as surface (within the tolerance) is closed. Off: it
    # saves 10-26 % of the flight time, but it also closed a door's last frontiers at the jamb's
    # corner and ended runs `complete` with a room unseen (docs/benchmarks.md, session 7); and
    # without loop closures, drifted neighbour views put vertices on walls they never were on.
    close_on_surface: bool = False
    surface_tol_m: float = 0.15
    # A frontier vertex this close to one the vehicle flew to and looked at (placed along the pose
    # graph, from a keyframe at most ``looked_max_hops`` away), facing within
    # ``looked_same_way_rad`` of the way it was looked at, is the same frontier again: closed as
    # looked at. Without loop closures, each new view at one spot offered the vertex just looked
    # at, too shallow in the views taken there to close, and the vehicle went back for it every
    # 16 s until its time limit (room seed 8, coverage 0.91). Facing another way, it looks into
    # other space: without that test, loop closures on, a door's frontiers were closed that way
    # and a room went unseen (apartment seed 5, coverage 0.77). 0 disables.
    looked_radius_m: float = 0.5
    looked_max_hops: int = 60
    looked_same_way_rad: float = math.radians(45.0)

    @property
    def clearance_m(self) -> float:
        return self.body_radius_m + self.clearance_margin_m


@dataclass(frozen=True, slots=True)
class Target:
    """Where to go, in the current keyframe's frame: position and the yaw to hold there."""

    x_m: float
    y_m: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class Decision:
    """The planner's answer for one step."""

    mode: Mode
    target: Target
    goal: FrontierKey | None = None
    relocalize_to: int | None = None  # the vehicle has reached this keyframe of the route
    want_keyframe: bool = False  # take a new view here (a goal was reached)


@dataclass(slots=True)
class _Goal:
    key: FrontierKey
    local_xy: tuple[float, float]  # goal point in the frontier keyframe's frame
    look_local_rad: float  # yaw to hold at the goal, in the frontier keyframe's frame
    selected_s: float
    deadline_s: float
    arrived_s: float | None = None
    path: FloatArray | None = None  # waypoints to the goal point, in the frontier keyframe's frame
    approach: bool = False  # only as near as the free space leads, to look again from there
    eased: bool = False  # its path keeps only a leg's clearance: found blocked, that is a failed try
    start_local_xy: tuple[float, float] = (math.nan, math.nan)  # where it was taken, same frame
    looking_in: bool = False  # on its last metre, its path seen: turning to look while flying in


@dataclass(slots=True)
class _Route:
    keyframes: list[int]  # remaining route, next waypoint first; the last one holds the frontier
    target_keyframe: int
    size_m: float = 0.0  # the shortest frontier run it is flown for (0: down to the fragment size)


@dataclass(slots=True)
class _Candidate:
    key: FrontierKey
    goal_xy: FloatArray  # in the current frame
    look_rad: float
    score: float
    path: FloatArray | None = None  # waypoints through free space when no straight path is clear
    approach: bool = False  # a step nearer a frontier out of reach, not a goal that sees it
    eased: bool = False  # its path was found by the grid at a leg's clearance

    @property
    def aim_xy(self) -> FloatArray:
        """Where to fly first: the path's first waypoint, or the goal point itself."""
        return self.goal_xy if self.path is None else self.path[0]


@dataclass(slots=True)
class _Leg:
    """Waypoints to the next route keyframe, kept in the frame they were planned in."""

    frame_id: int
    keyframe_id: int
    points: FloatArray
    ends_short: bool = False  # snapped to free space short of the keyframe (taken near a wall)
    flown: bool = False  # along the way flown between the two keyframes (see LocalMap.flown_between)


@dataclass(frozen=True, slots=True)
class _Replans:
    """How often the leg ``frame_id`` -> ``keyframe_id`` was planned again from one spot."""

    frame_id: int
    keyframe_id: int
    x_m: float
    y_m: float
    count: int


@dataclass(slots=True)
class FrontierPlanner:
    """Stateful goal selection; pure: every input comes in through :meth:`plan`."""

    params: PlannerParams = field(default_factory=PlannerParams)
    goal: _Goal | None = None
    route: _Route | None = None
    attempts: dict[FrontierKey, int] = field(default_factory=dict)
    set_aside: set[FrontierKey] = field(default_factory=set)
    _origin_only: set[FrontierKey] = field(default_factory=set)  # its last try: from its keyframe's origin
    # (keyframe, the vertex's position and the heading it was looked at from, in its frame)
    _looked: dict[int, list[tuple[float, float, float]]] = field(default_factory=dict)
    # (frame, map size, loop closures) -> those places in that frame, see _looked_in; None when
    # a place was added since
    _looked_memo: tuple[tuple[int, int, int], FloatArray] | None = None
    blocked_legs: set[tuple[int, int]] = field(default_factory=set)  # (from, to) seen blocked
    closed_on_sight: int = 0  # frontiers closed because the vehicle looked at them from their goal
    closed_on_surface: int = 0  # frontiers closed because the newest scan sees a surface right there
    # keyframe -> (map size, loop closures) when its frontiers were last closed through the graph
    _graph_checked: dict[int, tuple[int, int]] = field(default_factory=dict)
    _fresh_checks_left: int = 0  # graph checks after a loop closure still allowed in this step
    _sliver_checks_left: int = 0  # sliver judgements still allowed in this step
    _map_at_last_plan: tuple[int, int] = (-1, -1)  # (keyframes, loop closures) when plan() last ran
    _frame_id: int = -1  # this step's keyframe (its view is built): slivers are judged in it
    _live: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))
    _turn_first_rad: float = 0.0  # this step's limit (params', within the sensor's view)
    _progress_target: int | None = None
    _progress_s: float = 0.0
    _progress_hops: int = 0  # fewest route keyframes left to the progress target so far
    _leg: _Leg | None = None
    _replans: _Replans | None = None
    # keyframe -> when its frontiers were last tried in vain (from its origin, or no route left)
    _tried_in_vain: dict[int, float] = field(default_factory=dict)
    _stall_noted: bool = False  # see note_stall
    _stalled: bool = False  # this plan's: the first leg or goal it checks is blocked
    _arrived_at: int | None = None  # route keyframe last arrived at (its origin, or its leg's end)
    _cooling: dict[FrontierKey, float] = field(default_factory=dict)  # dropped goal -> until when
    # goal -> where it was last dropped as blocked (keyframe, vehicle position in its frame)
    _dropped_at: dict[FrontierKey, tuple[int, FloatArray]] = field(default_factory=dict)
    _failed_s: dict[FrontierKey, float] = field(default_factory=dict)  # when a try last failed
    _speed_mps: float = 0.0
    _velocity: FloatArray = field(default_factory=lambda: np.zeros(2))
    _live_view: Callable[[], shapely.Geometry] | None = None
    _live_surface: Callable[[FloatArray, float], NDArray[np.bool_]] | None = None
    _live_hidden: Callable[[FloatArray, float], NDArray[np.bool_]] | None = None
    _grids: dict[float, tuple[LocalView, FreeSpaceGrid]] = field(default_factory=dict)  # by clearance
    _grid_tried: tuple[LocalView, int, int] | None = None  # (view, cell): the grid found nothing there
    _live_floor_m: float = 0.0  # see _live_floor

    def plan(
        self,
        local_map: LocalMap,
        frame_id: int,
        vehicle: Pose2,
        stamp_s: float,
        live_obstacles_xy: FloatArray | None = None,
        velocity_xy: tuple[float, float] | None = None,
        live_view: Callable[[], shapely.Geometry] | None = None,
        live_surface: Callable[[FloatArray, float], NDArray[np.bool_]] | None = None,
        half_fov_rad: float | None = None,
        live_hidden: Callable[[FloatArray, float], NDArray[np.bool_]] | None = None,
    ) -> Decision:
        """Next target for a vehicle at ``vehicle`` (in keyframe ``frame_id``'s frame).

        ``live_obstacles_xy`` are the newest scan's returns in the same frame: every path is also
        checked against them (thesis 2.9.2: the current view must not head into an obstacle), so a
        drifted neighbour view can never clear a path the sensor sees blocked now. ``velocity_xy``
        (m/s, same frame) gates waypoint arrival: one counts as reached only once slow enough.
        ``live_view`` builds the newest scan's free-space polygon (same frame) on demand: paths
        through free space trust it over older, drifted views where they disagree.
        ``live_surface(points, tol_m)`` says which points (same frame) the newest scan sees as
        surface: a frontier vertex there is a wall, not a frontier (nothing lies beyond it).
        ``half_fov_rad`` is the sensor's half field of view: a path must lie inside it to be flown
        without turning first (see ``PlannerParams.turn_first_rad``). ``live_hidden(points,
        depth_m)`` says which points the newest scan sees hidden more than that behind a surface.
        """
        view = local_map.view(frame_id)
        self._stalled, self._stall_noted = self._stall_noted, False  # for this plan's leg or goal only
        self._turn_first_rad = self.params.turn_first_rad
        if half_fov_rad is not None:
            inside = half_fov_rad - self.params.fov_edge_margin_rad
            self._turn_first_rad = max(0.0, min(self._turn_first_rad, inside))
        here = np.array([vehicle.x_m, vehicle.y_m])
        self._live = np.zeros((0, 2)) if live_obstacles_xy is None else live_obstacles_xy
        self._velocity = np.zeros(2) if velocity_xy is None else np.array(velocity_xy, dtype=np.float64)
        self._speed_mps = float(np.hypot(*self._velocity))
        self._live_view = live_view
        self._live_surface = live_surface
        self._live_hidden = live_hidden
        self._cooling = {k: t for k, t in self._cooling.items() if t > stamp_s}
        self._fresh_checks_left = self.params.fresh_graph_checks_per_step
        # Slivers are judged only in a step that found the map as the last one left it: a new
        # keyframe or loop closure already made this one of the dearest (its views rebuilt, its
        # frontiers weighed afresh), and a frontier not judged yet counts as open meanwhile.
        self._frame_id = frame_id
        map_now = (len(local_map), local_map.loop_closures)
        self._sliver_checks_left = self.params.sliver_checks_per_step if map_now == self._map_at_last_plan else 0
        self._map_at_last_plan = map_now
        required = self._required_clearance(view, here)
        self._live_floor_m = self._live_floor(here)

        if self.goal is not None:
            decision = self._follow_goal(local_map, frame_id, view, vehicle, here, required, stamp_s)
            if decision is not None:
                return decision

        best = self._select_local(local_map, frame_id, view, vehicle, here, required)
        if best is not None:
            self.route = None
            self._commit(local_map, frame_id, best, here, stamp_s)
            return self._fly(vehicle, best.aim_xy, best.look_rad, Mode.EXPLORING, best.key)

        return self._backtrack(local_map, frame_id, view, vehicle, here, required, stamp_s)

    @property
    def pursuing(self) -> bool:
        """On its way: a goal not reached yet, or a route back."""
        return (self.goal is not None and self.goal.arrived_s is None) or self.route is not None

    def note_stall(self) -> None:
        """The vehicle has stood still on its way (see ``ExplorerParams.stall_s``): the next
        plan takes the leg or goal it is on as blocked, as when the sensor sees it so."""
        self._stall_noted = True

    # -- the committed goal ---------------------------------------------------------------------

    def _follow_goal(
        self,
        local_map: LocalMap,
        frame_id: int,
        view: LocalView,
        vehicle: Pose2,
        here: FloatArray,
        required: float,
        stamp_s: float,
    ) -> Decision | None:
        goal = self.goal
        assert goal is not None
        kf = local_map.keyframes[goal.key.keyframe_id]
        if goal.arrived_s is None:  # taken in a step that could not judge it, perhaps
            self._judge_slivers(local_map, goal.key.keyframe_id, np.array([goal.key.index], dtype=np.intp))
        # Closed (seen), unless seen while looking in: the view on arrival is still to come, and
        # it sees round the vertex, where the one that closed it, taken turning, did not.
        closed = kf.kinds[goal.key.index] != 1 and not (goal.looking_in and goal.arrived_s is None)
        if closed or goal.key in self.set_aside:
            self.goal = None
            return None
        pose = view.poses.get(goal.key.keyframe_id)
        if pose is None:
            pose = local_map.pose_in(frame_id, goal.key.keyframe_id)
        if self._off_surfaces(local_map, goal.key.keyframe_id, pose, np.array([goal.key.index])).size == 0:
            self.goal = None  # the sensor now sees a wall right at it
            return None
        gx, gy = pose.apply_point(*goal.local_xy)
        goal_xy = np.array([gx, gy])
        look = wrap_angle(goal.look_local_rad + pose.yaw_rad)
        dist = float(np.hypot(*(goal_xy - here)))
        facing = abs(wrap_angle(look - vehicle.yaw_rad)) <= self.params.look_reached_rad
        if goal.arrived_s is None and dist <= self.params.goal_reached_m and facing:
            goal.arrived_s = stamp_s
            return Decision(Mode.EXPLORING, Target(gx, gy, look), goal.key, want_keyframe=True)
        if goal.arrived_s is not None and stamp_s - goal.arrived_s >= self.params.settle_s:
            # Looked at it from its goal and it stays open: the space is seen, the vertex is stale
            # (its closing view is not in its neighbourhood). So are its close neighbours. Not
            # after an approach: that only came nearer, and its new view judges what is left.
            # Unless the vertex lies well behind the surface the vehicle faces: then the goal was
            # placed by drift on the wrong side of a wall (a view through a door, placed in the
            # room next door), nothing was looked at, and it is a failed try. Closed as looked
            # at, lshape seed 2 (in a variant) lost the room behind that door: `complete` at 0.96.
            if not goal.approach:
                vertex = pose.apply(kf.polygon.vertices_xy[goal.key.index : goal.key.index + 1])
                hidden = self._live_hidden is not None and bool(
                    self._live_hidden(vertex, self.params.hidden_depth_m)[0]
                )
                if hidden:
                    self._failed(goal.key, stamp_s)
                    self._drop(local_map, frame_id, here, goal.key, stamp_s)
                    return None
                # Remembered only now, once it counts as looked at: the place of a hidden vertex,
                # behind the wall, is where the corridor beyond it lies in truth, and it closed
                # that corridor's own frontiers as looked at (apartment seed 9, in a variant:
                # `complete` at coverage 0.79, two rooms unseen).
                self._looked.setdefault(frame_id, []).append((float(vertex[0, 0]), float(vertex[0, 1]), look))
                self._looked_memo = None
                self._close_looked_at(local_map, frame_id, goal.key)
            self.goal = None
            return None
        if goal.arrived_s is None and stamp_s > goal.deadline_s:
            self._failed(goal.key, stamp_s)
            self.goal = None
            return None
        if goal.path is not None and goal.arrived_s is None:
            pts = pose.apply(goal.path)
            pts = self._past_corners(pts, here)
            goal.path = goal.path[-pts.shape[0] :]
            # Every leg of a path through the free-space grid, the last one too, was planned clear
            # of the map's walls and is judged by the newest scan as it is flown. (The goal has a
            # path because its straight line failed the stricter test: asked again of the last
            # leg, that test dropped the goal the step after it was taken, a door's frontiers
            # one after another until they were set aside.)
            stalled = self._stalled  # a stall is no line to go round
            if self._leg_blocked(vehicle, here, pts[0], required):
                # Only the line grazes a return (a passage about as wide as the path's clearance,
                # the scan a few centimetres off the map): go on through the scan's free space,
                # as a route's leg does. Dropped, with a try counted each time, a cave's only
                # passage had both its frontiers set aside in 13 s: `unreachable_frontiers_left`
                # at coverage 0.55 (cave seed 7, in a variant, session 46).
                aim = self._sidestep(here, pts[0], required) if self.params.sidestep_goal_legs and not stalled else None
                if aim is not None:
                    goal.path = np.vstack((pose.inverse().apply(aim.reshape(1, 2)), goal.path))
                    return self._fly(vehicle, aim, look, Mode.EXPLORING, goal.key)
                if dist <= self.params.near_goal_m:
                    # Its last leg blocked this near, look from here: a goal is a place to look
                    # from, and one 0.4 m off sees the frontier as well. (Found blocked 0.42 m short,
                    # a goal by a wall counted a failed try; from its keyframe it was out of reach,
                    # and room seed 13 set it aside at coverage 1.000.)
                    goal.local_xy = pose.inverse().apply_point(float(here[0]), float(here[1]))
                    goal.path = None
                    return self._fly(vehicle, here, look, Mode.EXPLORING, goal.key)
                if goal.eased:  # the way the full clearance did not find: blocked, it is a try
                    self._failed(goal.key, stamp_s)
                self._drop(local_map, frame_id, here, goal.key, stamp_s)
                return None
            return self._fly(vehicle, pts[0], look, Mode.EXPLORING, goal.key)
        if goal.arrived_s is not None:
            # Settle where it arrived: a new keyframe may re-express the goal a little elsewhere
            # (another chain of the graph), and chasing that would creep towards walls.
            return Decision(Mode.EXPLORING, Target(vehicle.x_m, vehicle.y_m, look), goal.key)
        stalled, self._stalled = self._stalled, False
        if stalled or (
            dist > self.params.goal_reached_m and not self._still_accessible(view, pose, here, goal, goal_xy, required)
        ):
            self._drop(local_map, frame_id, here, goal.key, stamp_s)
            return None
        decision = self._fly(vehicle, goal_xy, look, Mode.EXPLORING, goal.key)
        flying_in = decision.target.x_m == gx and decision.target.y_m == gy  # not turning first
        if dist <= self.params.look_ahead_m and (goal.looking_in or flying_in):
            goal.looking_in = True
            return Decision(Mode.EXPLORING, Target(gx, gy, look), goal.key)
        return decision

    def _still_accessible(
        self, view: LocalView, pose: Pose2, here: FloatArray, goal: _Goal, goal_xy: FloatArray, required: float
    ) -> bool:
        """The committed goal's straight path is still accessible. Where the vehicle has not moved
        since it was taken, only the newest scan can change that: a view taken there a step later
        (turning to it) has another neighbourhood, which judged it blocked, and the vehicle went
        back to the keyframe it was taken from, took it again, turned, took a view, dropped it...
        for two minutes on one spot (offices2 seed 8: 1072 keyframes, against some 400)."""
        start = np.array(pose.apply_point(*goal.start_local_xy))
        if not float(np.hypot(*(here - start))) <= self.params.goal_reached_m:  # moved (or unknown)
            return self._accessible(view, here, goal_xy, required)
        return bool(self._clear_of_live(here, goal_xy.reshape(1, 2), required)[0])

    def _leg_required(self, required: float) -> float:
        """A leg through known free space needs the body radius clear, not the whole margin."""
        return min(required, self._leg_clearance())

    def _leg_floor(self, required: float) -> float:
        """What a leg keeps from the newest returns as it is flown: a leg's clearance, or the
        live floor when that is more."""
        return max(self._leg_required(required), self._live_floor_m)

    def _leg_clearance(self) -> float:
        """The clearance a grid path for a leg keeps: the body radius and leg margin."""
        return self.params.body_radius_m + self.params.leg_margin_m

    def _path_clear_of_live(self, here: FloatArray, path: FloatArray, required: float) -> bool:
        """Every leg of a path from ``here`` keeps from the newest returns what a leg is held to
        as it is flown (:meth:`_leg_blocked`). The grid at a leg's clearance lets a path pass a
        return closer than that (its cells are 0.15 m): taken, such a goal was dropped at once,
        the next one the same, fifty in turn for 20 minutes on one spot (offices2 seed 4)."""
        if self._live.shape[0] == 0:
            return True
        segments = np.stack((np.vstack((here, path[:-1])), path), axis=1)
        return bool(point_segment_distances(self._live, segments).min() >= self._leg_floor(required))

    def _live_floor(self, here: FloatArray) -> float:
        """The least clearance from the newest returns any path needs: the body radius and leg
        margin, or (already closer to one) nearly what the vehicle has now. The setpoint lead
        holds the vehicle that far from returns whatever the planner asks; a path the planner
        let closer (its clearance eased by a map wall drifted onto the vehicle) held it still
        in a doorway until the route timed out, over and over (hotel seed 7)."""
        if self._live.shape[0] == 0:
            return 0.0
        now = float(np.min(np.hypot(*(self._live - here).T)))
        return min(self._leg_clearance(), 0.95 * now)

    def _past_corners(self, path: FloatArray, here: FloatArray) -> FloatArray:
        """The path without the corners already passed (its last point always stays)."""
        while path.shape[0] > 1 and self._reached(path[0], here, self.params.corner_reached_m):
            path = path[1:]
        return path

    def _drop(self, local_map: LocalMap, frame_id: int, here: FloatArray, key: FrontierKey, stamp_s: float) -> None:
        """Give up a goal found blocked on the way, and leave it alone for a while: two goals
        that block each other in turn must not hold the vehicle flipping between them. Found
        blocked again from where it was dropped before, it counts a failed try: lshape seed 1
        (perfect odometry, no loop closures) took one goal whose path only the sensor, once
        facing it, saw blocked, dropped it, flew 3 m back along its route and returned, every
        10 s for 700 s. (Counted wherever it was found blocked again, two runs of 90 with loop
        closures set a frontier aside at coverage 1.000 that they had closed before.)"""
        self.goal = None
        self._cooling[key] = stamp_s + self.params.blocked_cooldown_s
        before = self._dropped_at.get(key)
        if before is not None and before[0] in local_map.keyframes:
            then = local_map.pose_in(frame_id, before[0]).apply(before[1].reshape(1, 2))[0]
            if float(np.hypot(*(here - then))) <= self.params.goal_reached_m:
                self._failed(key, stamp_s)
        self._dropped_at[key] = (frame_id, here.copy())

    def _leg_blocked(self, vehicle: Pose2, here: FloatArray, wp: FloatArray, required: float) -> bool:
        """The newest scan sees the leg to ``wp`` blocked (judged once facing it: the sensor looks
        ahead), or the vehicle stood still on it (:meth:`note_stall`). A leg through free space
        needs the body radius clear, not the whole margin."""
        if self._stalled:
            self._stalled = False
            return True
        travel = float(np.arctan2(*(wp - here)[::-1]))
        facing = abs(wrap_angle(travel - vehicle.yaw_rad)) <= self._turn_first_rad
        if not (facing and self._live.shape[0]):
            return False
        return _segment_clearance(here, wp, self._live) < self._leg_floor(required)

    def _commit(self, local_map: LocalMap, frame_id: int, c: _Candidate, here: FloatArray, stamp_s: float) -> None:
        # A goal taken ends the route (each caller drops it): a later route, to the same target
        # too, starts its progress watchdog afresh. Kept, the watchdog counted the minutes spent
        # exploring on the way as a stalled route, and the first step of the next route to that
        # target failed its frontiers a third time: set aside, the space beyond them long seen
        # (campus seed 4, in a variant, `unreachable_frontiers_left` at coverage 0.99998).
        self._progress_target = None
        pose = local_map.pose_in(frame_id, c.key.keyframe_id).inverse()
        lx, ly = pose.apply_point(float(c.goal_xy[0]), float(c.goal_xy[1]))
        dist = float(np.hypot(*(c.goal_xy - here)))
        if c.path is not None:
            dist = float(np.sum(np.hypot(*np.diff(np.vstack((here, c.path)), axis=0).T)))
        budget = max(self.params.goal_timeout_min_s, 3.0 * dist / self.params.cruise_speed_mps)
        path = None if c.path is None else pose.apply(c.path)
        look = wrap_angle(c.look_rad + pose.yaw_rad)
        sx, sy = pose.apply_point(float(here[0]), float(here[1]))
        self.goal = _Goal(
            c.key,
            (lx, ly),
            look,
            stamp_s,
            stamp_s + budget,
            path=path,
            approach=c.approach,
            start_local_xy=(sx, sy),
            eased=c.eased,
        )
        self._arrived_at = None

    def _off_surfaces(
        self, local_map: LocalMap, keyframe_id: int, pose: Pose2, idx: NDArray[np.intp], always: bool = False
    ) -> NDArray[np.intp]:
        """The frontier vertices ``idx`` of a keyframe (at ``pose`` in the current frame) that
        the newest scan does not see as surface. Those it does are closed: a wall their own view
        saw only as the end of its range (or not at all) stands right there, nothing lies
        beyond, and no flight is needed to find that out. Checked for goal candidates when
        ``close_on_surface`` is on, and (``always``) for those out of reach from their own origin."""
        if self._live_surface is None or not (always or self.params.close_on_surface) or idx.size == 0:
            return idx
        kf = local_map.keyframes[keyframe_id]
        on = self._live_surface(pose.apply(kf.polygon.vertices_xy[idx]), self.params.surface_tol_m)
        if on.any():
            local_map.close_frontiers(keyframe_id, idx[on], VertexKind.OBSTACLE)
            self.closed_on_surface += int(np.count_nonzero(on))
        return idx[~on]

    def _close_looked_at(self, local_map: LocalMap, frame_id: int, key: FrontierKey) -> None:
        """The vehicle looked at this frontier from its goal, a view was taken there, and it stays
        open: nothing beyond it can be seen from where a frontier is explored (a wall the vertex's
        own view missed, or a view that drifted off it). It and its close neighbours are closed:
        by eq. 2.15 against the current view where that saw beyond them, as looked at otherwise."""
        kf = local_map.keyframes[key.keyframe_id]
        xy = kf.polygon.vertices_xy
        near = np.hypot(*(xy - xy[key.index]).T) <= self.params.stale_radius_m
        near[key.index] = True
        idx = np.flatnonzero(near & (kf.kinds == KIND_FRONTIER))
        if idx.size:
            seen = local_map.close_seen_from(frame_id, key.keyframe_id, idx)
            stale = idx[~seen]
            local_map.close_frontiers(key.keyframe_id, stale)
            self.closed_on_sight += int(stale.size)

    def unreachable(self, local_map: LocalMap) -> list[FrontierKey]:
        """Frontiers set aside after failed tries that no view has closed since."""
        return [
            k
            for k in sorted(self.set_aside, key=lambda k: (k.keyframe_id, k.index))
            if local_map.keyframes[k.keyframe_id].kinds[k.index] == KIND_FRONTIER
        ]

    def _failed(self, key: FrontierKey, stamp_s: float, at_origin: bool = False) -> None:
        """Count a failed try. Once per cooldown: a goal dropped as blocked is out of the running
        for that long, and finding it so again step after step (from a keyframe's origin, say)
        is one try, not many: it must not be set aside before it was tried again.
        ``at_origin``: the try was made from its keyframe's origin."""
        last = self._failed_s.get(key)
        if last is not None and stamp_s - last < self.params.blocked_cooldown_s:
            return
        self._failed_s[key] = stamp_s
        n = self.attempts.get(key, 0) + 1
        self.attempts[key] = n
        if n >= self.params.max_attempts:
            # Before it is set aside, one more try from its own keyframe's origin, where its
            # vertex lies exactly where its scan put it; placed in any other (drifted) frame it
            # may lie in a wall. (Every later view of corridor seed 5 put a range-end vertex
            # 0.3-0.5 m inside the corridor's wall, took it from there, dropped it twice and set
            # it aside at coverage 1.000; from its origin the look closes it.)
            if at_origin or key in self._origin_only:
                self.set_aside.add(key)
            else:
                self._origin_only.add(key)

    # -- rapid selection in the current neighbourhood -------------------------------------------

    def _candidates(
        self,
        local_map: LocalMap,
        view: LocalView,
        vehicle: Pose2,
        here: FloatArray,
        only_keyframe: int | None = None,
        dense: bool = False,
        limit: int | None = None,
        min_size_m: float | None = None,
    ) -> list[_Candidate]:
        """Goal candidates for the open frontiers in view (of one keyframe only, if given), best
        first (least change of heading, then nearest), inside known free space; at most ``limit``;
        runs at least ``min_size_m`` long (default: ``min_frontier_size_m``)."""
        p = self.params
        key_ids: list[NDArray[np.intp]] = []  # keyframe id and vertex index of each goal
        key_idx: list[NDArray[np.intp]] = []
        goals: list[FloatArray] = []
        looks: list[FloatArray] = []
        # A goal dropped as blocked cools down before it is taken again, but not from its own
        # keyframe's origin: that is another way to it, and the only one left when the route
        # led there for it (skipping it there would count a failed try never made). A frontier
        # that used up its tries elsewhere is tried once more from there only (see _failed).
        skip: dict[int, list[int]] = {}
        for key in self.set_aside if dense else self.set_aside | self._cooling.keys() | self._origin_only:
            skip.setdefault(key.keyframe_id, []).append(key.index)
        looked = self._looked_in(local_map, view.keyframe_id)
        if min_size_m is None:
            min_size_m = p.min_frontier_size_m
        for k, pose in view.poses.items():
            if only_keyframe is not None and k != only_keyframe:
                continue
            kf = local_map.keyframes[k]
            idx = targetable_indices(kf, min_size_m)
            if k in skip and idx.size:
                idx = idx[~np.isin(idx, skip[k])]
            if idx.size == 0:
                continue
            idx = self._off_surfaces(local_map, k, pose, idx)
            if idx.size and looked.shape[0]:
                # The same frontier again: at a place looked at, facing the same way.
                vc = pose.apply(kf.polygon.vertices_xy[idx])
                nc = pose.rotate(kf.polygon.outward_xy[idx])
                near = np.hypot(vc[:, None, 0] - looked[None, :, 0], vc[:, None, 1] - looked[None, :, 1])
                same_way = nc[:, None, 0] * looked[None, :, 2] + nc[:, None, 1] * looked[None, :, 3] >= math.cos(
                    p.looked_same_way_rad
                )
                again = ((near <= p.looked_radius_m) & same_way).any(axis=1)
                if again.any():
                    local_map.close_frontiers(k, idx[again])
                    self.closed_on_sight += int(np.count_nonzero(again))
                    idx = idx[~again]
            if idx.size == 0:
                continue
            v = kf.polygon.vertices_xy[idx]
            n = kf.polygon.outward_xy[idx]
            normal_pt = v - p.standoff_m * n
            ray_len = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
            ray_pt = v * np.maximum(ray_len - p.standoff_m, 0.0) / ray_len
            variants = [normal_pt, ray_pt]
            if dense:
                # From a keyframe's origin, try harder: goals nearer and farther, and shifted
                # sideways (a frontier beside a door jamb has its plain goals too close to it).
                side = np.column_stack((-n[:, 1], n[:, 0]))
                for back in (0.6 * p.standoff_m, 1.5 * p.standoff_m):
                    variants.append(v - back * n)
                for shift in (-p.side_shift_m, p.side_shift_m):
                    for back in (p.standoff_m, 1.5 * p.standoff_m):
                        variants.append(v - back * n + shift * side)
            for pts in variants:
                # Face the vertex from the goal: along its normal from the normal point, along the
                # ray from a goal on its ray (looking along the normal from there, a shadow edge's
                # vertex lay 90 degrees off the view taken on arrival, which then closed it and its
                # neighbours as looked at: a room behind a door was never entered).
                to_vertex = v - pts
                look_local = np.arctan2(to_vertex[:, 1], to_vertex[:, 0])
                # A goal at the keyframe's own origin, facing about its heading, would take the
                # keyframe's own view again: nothing to learn (a vertex near the origin has its
                # ray goal there). Flown to, it was looked at and closed, the arrival's view
                # found it again as a new vertex, and apartment 5 turned on one spot for 20 min.
                new_view = (np.hypot(pts[:, 0], pts[:, 1]) > p.goal_reached_m) | (np.abs(look_local) >= p.same_view_rad)
                goals.append(pose.apply(pts[new_view]))
                looks.append(wrap_angles(look_local[new_view] + pose.yaw_rad))
                key_ids.append(np.full(int(new_view.sum()), k, dtype=np.intp))
                key_idx.append(idx[new_view])
        if not goals:
            return []
        g = np.vstack(goals)
        look = np.concatenate(looks)
        delta = g - here
        dist = np.hypot(delta[:, 0], delta[:, 1])
        travel = np.arctan2(delta[:, 1], delta[:, 0])
        heading = np.where(dist > 0.5, travel, look)
        change = np.abs(wrap_angles(heading - vehicle.yaw_rad))
        score = change + p.distance_weight_rad_per_m * dist
        inside = view.holds(g)
        order = np.argsort(score, kind="stable")
        order = order[inside[order]][:limit]
        ids, ind = np.concatenate(key_ids)[order], np.concatenate(key_idx)[order]
        return [
            _Candidate(FrontierKey(int(k), int(i)), g[j], float(look[j]), float(score[j]))
            for k, i, j in zip(ids, ind, order, strict=True)
        ]

    def _looked_in(self, local_map: LocalMap, frame_id: int) -> FloatArray:
        """The places goals were reached and looked at, in the current keyframe's frame, with the
        heading they were looked at from (rows x, y, cos, sin; placed along the pose graph, from
        keyframes at most ``looked_max_hops`` away, and no farther than the map's drift margin per
        hop keeps within ``looked_radius_m``)."""
        if self.params.looked_radius_m <= 0.0 or not self._looked:
            return np.zeros((0, 4))
        # Placed along a chain with more drift than the radius, a place looked at is nowhere in
        # particular: as far as the map's drift margin keeps it within the radius, no farther.
        max_hops = self.params.looked_max_hops
        per_hop = local_map.params.chain_margin_per_hop_m
        if per_hop > 0.0:
            max_hops = min(max_hops, int(self.params.looked_radius_m / per_hop))
        key = (frame_id, len(local_map), local_map.loop_closures)
        if self._looked_memo is not None and self._looked_memo[0] == key:
            return self._looked_memo[1]
        # The graph's cached walk (closing through the graph walks it too), not a walk of its own.
        reach = local_map.graph.reached(frame_id, max_hops)
        near = (reach.hops <= max_hops) & np.isin(reach.ids, np.fromiter(self._looked, dtype=np.intp))
        out = []
        for k, (x, y, yaw_rad) in zip(reach.ids[near], reach.poses[near], strict=True):
            at = np.array(self._looked[int(k)])
            pose = Pose2(float(x), float(y), float(yaw_rad))
            yaw = at[:, 2] + pose.yaw_rad
            out.append(np.column_stack((pose.apply(at[:, :2]), np.cos(yaw), np.sin(yaw))))
        looked = np.vstack(out) if out else np.zeros((0, 4))
        self._looked_memo = (key, looked)
        return looked

    def _select_local(
        self,
        local_map: LocalMap,
        frame_id: int,
        view: LocalView,
        vehicle: Pose2,
        here: FloatArray,
        required: float,
        only_keyframe: int | None = None,
    ) -> _Candidate | None:
        dense = only_keyframe is not None
        limit = self.params.max_candidates_checked * (8 if dense else 1)
        # At a route's target, its fragments too when the route was for them.
        size = self.params.min_frontier_size_m
        if dense and self.route is not None and self.route.target_keyframe == only_keyframe:
            size = max(self.params.fragment_size_m, min(size, self.route.size_m))
        candidates = self._candidates(local_map, view, vehicle, here, only_keyframe, dense, limit, size)
        if candidates:
            # The best candidate still open once views along the graph are checked, with a clear
            # straight path; the graph is checked only for those the clearance tests pass.
            goals = np.array([c.goal_xy for c in candidates])
            first = self._first_accessible(
                view, here, goals, required, lambda i: self._open_through_graph(local_map, candidates[i].key)
            )
            if first is not None:
                return candidates[first]
        # No straight path: look for paths through the known free space (a frontier seen through a
        # door at an angle). Once per view and place, unless asked at a keyframe's origin. The
        # graph is checked candidate by candidate, up to the first with a path (each check may
        # walk the whole pose graph; together they were a quarter of the dearest steps).
        tried = (view, math.floor(here[0]), math.floor(here[1]))
        last = self._grid_tried
        if not dense and last is not None and last[0] is view and last[1:] == tried[1:]:
            return None
        # At a keyframe's origin, at the full clearance first, then at a leg's (what each leg of
        # such a path is held to as it is flown): a 0.9 m door is closed to the grid at 0.4 m,
        # and a room behind one, seen from the corridor, had its frontiers set aside from there
        # (apartment seed 15). Not from anywhere else: such goals taken wherever the vehicle
        # was, each found blocked further on, held it on one spot until the time limit
        # (room seed 1 without loop closures).
        searched = False
        clearances = (self.params.clearance_m, self._leg_clearance()) if dense else (self.params.clearance_m,)
        for clearance in clearances:
            eased = clearance < self.params.clearance_m  # its paths may pass returns too close
            reach: Reach | None = None
            for c in candidates:
                if not self._open_through_graph(local_map, c.key):  # asked again, it is cached
                    continue
                if reach is None:
                    searched = True
                    reach = self._reach(view, here, clearance)
                    if reach is None:
                        break
                if not self._sees(local_map, view, c):
                    continue
                path = reach.path_to(c.goal_xy)
                if path is not None and (not eased or self._path_clear_of_live(here, path, required)):
                    c.path, c.eased = path, eased
                    return c
            if not searched:
                break  # no candidate is open
        if searched:
            self._grid_tried = tried
        return None

    def _sees(self, local_map: LocalMap, view: LocalView, c: _Candidate) -> bool:
        """From the candidate's goal the vehicle would see its vertex: the line between them,
        short of the vertex by ``sight_trim_m`` (a vertex may lie on a wall), crosses no wall in
        view. Candidates come from the view's keyframes, so the view places the vertex."""
        trim = self.params.sight_trim_m
        if trim <= 0.0 or view.obstacles.is_empty:
            return True
        kf = local_map.keyframes[c.key.keyframe_id]
        vertex = view.poses[c.key.keyframe_id].apply(kf.polygon.vertices_xy[c.key.index : c.key.index + 1])[0]
        to_vertex = vertex - c.goal_xy
        length = float(np.hypot(*to_vertex))
        if length <= trim:
            return True
        end = c.goal_xy + to_vertex * (length - trim) / length
        return not bool(shapely.intersects(shapely.LineString([c.goal_xy, end]), view.obstacles))

    def _open_through_graph(self, local_map: LocalMap, key: FrontierKey) -> bool:
        """Still open once views along the pose graph are checked too (a view that saw beyond it
        may not overlap the current one: the vehicle has been round the block since), and not a
        sliver."""
        self._check_through_graph(local_map, key.keyframe_id)
        self._judge_slivers(local_map, key.keyframe_id, np.array([key.index], dtype=np.intp))
        return bool(local_map.keyframes[key.keyframe_id].kinds[key.index] == KIND_FRONTIER)

    def _judge_slivers(self, local_map: LocalMap, keyframe_id: int, indices: NDArray[np.intp]) -> None:
        """Close those of these frontiers whose unseen space is only a sliver (slivers.py, in this
        step's view where it can), as far as the step's budget goes; the rest count as open until
        a later step judges them."""
        frame_id = self._frame_id
        if self._sliver_checks_left <= 0:
            return
        todo = local_map.unjudged_slivers(keyframe_id, indices, frame_id)[: self._sliver_checks_left]
        if todo.size:
            self._sliver_checks_left -= todo.size
            local_map.close_slivers(keyframe_id, todo, frame_id)

    def _reach(self, view: LocalView, here: FloatArray, clearance_m: float | None = None) -> Reach | None:
        """The wavefront through the view's free space (with the newest returns) from ``here``,
        keeping ``clearance_m`` (default: the planner's clearance) from walls and unknown space."""
        clearance = self.params.clearance_m if clearance_m is None else clearance_m
        cached = self._grids.get(clearance)
        if cached is None or cached[0] is not view:
            cached = (view, FreeSpaceGrid.build(view.shapes, view.walls_xy, clearance, self.params.grid))
            self._grids = {k: v for k, v in self._grids.items() if v[0] is view}
            self._grids[clearance] = cached
        live_view = None if self._live_view is None else self._live_view()
        return cached[1].with_live_scan(self._live, live_view).reach_from(here)

    # -- accessibility (2.9.2) ------------------------------------------------------------------

    def _required_clearance(self, view: LocalView, here: FloatArray) -> float:
        """The clearance a path must keep: the configured one, or (when the vehicle is already
        closer to a wall) nearly what it has now, so it can always move away."""
        now = math.inf
        if not view.obstacles.is_empty:
            now = float(shapely.distance(shapely.Point(here), view.obstacles))
        if self._live.shape[0]:
            now = min(now, float(np.min(np.hypot(*(self._live - here).T))))
        return min(self.params.clearance_m, 0.9 * now)

    def _accessible(self, view: LocalView, start: FloatArray, goal: FloatArray, required: float) -> bool:
        """Straight path inside known free space and clear of every obstacle edge in view."""
        return self._first_accessible(view, start, goal.reshape(1, 2), required) is not None

    def _first_accessible(
        self,
        view: LocalView,
        start: FloatArray,
        goals: FloatArray,
        required: float,
        keep: Callable[[int], bool] | None = None,
    ) -> int | None:
        """The first of the goals (K, 2) that :meth:`_accessible` holds for (and ``keep``, if
        given), None when none is. The clearance tests run for all goals at once; ``keep`` and
        free space (the dearest tests) are asked only of those that pass them, in order."""
        delta = goals - start
        length = np.hypot(delta[:, 0], delta[:, 1])
        ok = np.ones(goals.shape[0], dtype=bool)
        # The start may be closer to a wall than the clearance (so the vehicle can always move
        # away); the end may not, or a vehicle near a wall would creep along closer and closer.
        end = self.params.goal_clearance_m
        ok &= self._clear_of_live(start, goals, required)
        paths = shapely.linestrings(np.stack((np.broadcast_to(start, goals.shape), goals), axis=1))
        if not view.obstacles.is_empty:
            ok &= shapely.distance(shapely.points(goals), view.obstacles) >= end
            ok &= shapely.distance(paths, view.obstacles) >= required
        ok |= length < 1e-6  # no path: the vehicle is there, so only its place must be free
        for i in np.flatnonzero(ok):
            if keep is not None and not keep(int(i)):
                continue
            if length[i] < 1e-6:
                if view.holds(goals[i : i + 1])[0]:
                    return int(i)
                continue
            # The disc the vehicle's body covers is free by its presence: the part that must lie
            # in known free space starts at its edge. The vehicle may sit on a polygon's corner
            # (a keyframe's origin) or just behind it: 0.1 m behind a view's apex, every path out
            # of the vehicle's spot left the view at once, and rotunda seed 14 set every frontier
            # aside from there within 10 s (when the part began 5 cm along).
            lead = start + delta[i] * min(self.params.body_radius_m / float(length[i]), 0.5)
            if view.covers(shapely.LineString([lead, goals[i]])):
                return int(i)
        return None

    def _clear_of_live(self, start: FloatArray, goals: FloatArray, required: float) -> NDArray[np.bool_]:
        """For each straight path from ``start`` to one of the goals (K, 2): clear of the newest
        returns by ``required`` (at least the live floor), its end by ``goal_clearance_m``."""
        if self._live.shape[0] == 0:
            return np.ones(goals.shape[0], dtype=bool)
        ok = _segment_clearances(start, goals, self._live) >= max(required, self._live_floor_m)
        gap = goals[:, None, :] - self._live[None, :, :]
        ok &= np.hypot(gap[..., 0], gap[..., 1]).min(axis=1) >= self.params.goal_clearance_m
        return ok

    # -- classical fallback (2.9.3) -------------------------------------------------------------

    def _backtrack(
        self,
        local_map: LocalMap,
        frame_id: int,
        view: LocalView,
        vehicle: Pose2,
        here: FloatArray,
        required: float,
        stamp_s: float,
    ) -> Decision:
        if (
            self.route is None
            or self.route.target_keyframe not in local_map.keyframes
            or not self._has_live_targets(local_map, self.route.target_keyframe, self.route.size_m)
        ):
            self.route = self._find_route(local_map, frame_id)
            self._arrived_at = None
        if self.route is None:
            return Decision(Mode.COMPLETE, Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad))
        route = self.route
        # Progress watchdog: a target keyframe not reached in time (legs blocked one after
        # another, a waypoint never reached) counts a failed try for its frontiers.
        if self._route_stalled(route, stamp_s):
            self._fail_keyframe(local_map, route.target_keyframe, stamp_s, size_m=route.size_m)
            self.blocked_legs.clear()
            self.route = None
            self._progress_target = None
            return Decision(Mode.BACKTRACKING, Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad))
        # The route ends here: take the target keyframe's own frontiers from its origin, where
        # its polygon is star-shaped (or from where the leg to it ended, when the origin is too
        # close to a wall); those still out of reach count a failed try.
        at_target = self._arrived_at == frame_id or self._reached(np.zeros(2), here, self.params.waypoint_reached_m)
        if route.keyframes == [frame_id] and at_target:
            best = self._select_local(local_map, frame_id, view, vehicle, here, required, only_keyframe=frame_id)
            if best is not None:
                self.route = None
                self._commit(local_map, frame_id, best, here, stamp_s)
                return self._fly(vehicle, best.aim_xy, best.look_rad, Mode.EXPLORING, best.key)
            # Out of reach from the keyframe's own origin. Facing the way the keyframe looked,
            # the vehicle sees all of its polygon (star-shaped from there): those the newest scan
            # sees a wall right at are walls (a vertex its view left by a wall seen at a grazing
            # angle), not a failed try; set aside, they ended runs `unreachable_frontiers_left`
            # at coverage 1.000.
            if abs(wrap_angle(vehicle.yaw_rad)) > self.params.look_reached_rad:
                return Decision(Mode.BACKTRACKING, Target(vehicle.x_m, vehicle.y_m, 0.0))
            idx = np.array(self._targets(local_map, frame_id, route.size_m), dtype=np.intp)
            if self._off_surfaces(local_map, frame_id, Pose2.identity(), idx, always=True).size == 0:
                return Decision(Mode.BACKTRACKING, Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad))
            self._fail_keyframe(local_map, frame_id, stamp_s, at_origin=True, size_m=route.size_m)
            self._tried_in_vain[frame_id] = stamp_s
            self.route = None
            # Out of reach from here (seen through a door at an angle, say): before leaving, go as
            # near as the free space leads and look again; a new view there may open the way.
            near = self._approach(local_map, frame_id, view, here, route.size_m)
            if near is not None:
                self._commit(local_map, frame_id, near, here, stamp_s)
                return self._fly(vehicle, near.aim_xy, near.look_rad, Mode.EXPLORING, near.key)
            return Decision(Mode.BACKTRACKING, Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad))
        # Skip ahead to the farthest route keyframe in view that a straight path reaches.
        skip = 0
        for j in range(min(len(route.keyframes), self.params.shortcut_hops) - 1, 0, -1):
            k = route.keyframes[j]
            pose = view.poses.get(k)
            if (
                pose is not None
                and (frame_id, k) not in self.blocked_legs
                and self._accessible(view, here, np.array([pose.x_m, pose.y_m]), required)
            ):
                skip = j
                break
        nxt = route.keyframes[skip]
        pose = local_map.pose_in(frame_id, nxt)
        wp = np.array([pose.x_m, pose.y_m])
        if skip:
            points, fresh = wp[None, :], True
        else:
            points, fresh = self._leg_points(local_map, frame_id, view, here, nxt, wp, required)
        if self._leg_blocked(vehicle, here, points[0], required):
            if not fresh and self._may_replan(frame_id, nxt, here):  # plan again with the newest scan
                self._leg = None
                return Decision(Mode.BACKTRACKING, Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad))
            tried = skip > 0 or (self._leg is not None and self._leg.flown)  # skipping ahead: no edge
            flown = None if tried else local_map.flown_between(frame_id, nxt)
            if flown is not None:
                # Blocked straight (a keyframe taken out of the other's sight, across a wall from
                # it): fly back the way the vehicle came. Without it, the only route from here
                # was blocked and every frontier was set aside in turn while the vehicle hovered.
                self._leg = _Leg(frame_id, nxt, np.vstack((flown, wp)), flown=True)
                travel = float(np.arctan2(*(flown[0] - here)[::-1]))
                return self._fly(vehicle, flown[0], travel, Mode.BACKTRACKING, None)
            aim = self._sidestep(here, wp, required)
            if aim is not None:
                # Only the line is blocked (a waypoint drifted onto a wall of a narrow corridor,
                # older views' walls closing the free space around it): go on as the scan allows,
                # by a leg through the aim (kept, so turning to it does not undo the choice).
                self._leg = _Leg(frame_id, nxt, np.vstack((aim, wp)))
                travel = float(np.arctan2(*(aim - here)[::-1]))
                return self._fly(vehicle, aim, travel, Mode.BACKTRACKING, None)
            # The sensor sees this leg blocked now (a drifted or loop-closure leg cutting a
            # corner, no way round in view): never take it again; re-route around it, and only
            # when no route is left do the target's frontiers count a failed try.
            self.blocked_legs.add((frame_id, nxt))
            self._leg = None
            if skip == 0:
                self.route = self._find_route(local_map, frame_id, route.target_keyframe, route.size_m)
                if self.route is None:
                    self._fail_keyframe(local_map, route.target_keyframe, stamp_s, size_m=route.size_m)
                    self._tried_in_vain[route.target_keyframe] = stamp_s
            return Decision(Mode.BACKTRACKING, Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad))
        del route.keyframes[:skip]
        leg = self._leg
        # A leg snapped short of its keyframe (one taken close to a wall) ends where it ends:
        # waiting to get nearer would hold the vehicle there until the route times out.
        leg_flown = (
            leg is not None
            and leg.keyframe_id == nxt
            and leg.ends_short
            and points.shape[0] == 1
            and self._reached(points[0], here, self.params.corner_reached_m)
        )
        if leg_flown or self._reached(wp, here, self.params.waypoint_reached_m):
            self._progress_s = stamp_s
            self._leg = None
            self._arrived_at = nxt
            if len(route.keyframes) > 1:
                route.keyframes.pop(0)
            hold = (
                Target(vehicle.x_m, vehicle.y_m, vehicle.yaw_rad)
                if leg_flown
                else Target(pose.x_m, pose.y_m, pose.yaw_rad)
            )
            return Decision(Mode.BACKTRACKING, hold, relocalize_to=nxt)
        aim = points[0]
        if (
            nxt == route.target_keyframe
            and points.shape[0] == 1
            and float(np.hypot(*(aim - here))) <= self.params.waypoint_reached_m
        ):
            # Overshot the route's end (braking past the origin of its target, often the keyframe
            # just taken): back up to it facing the way that keyframe looked, as the vehicle will
            # once there. Turned round to face so short a hop, it turned back on arrival: 5 s on
            # the spot for half a metre (lshape seed 1). It has just flown through that space.
            return Decision(Mode.BACKTRACKING, Target(float(aim[0]), float(aim[1]), pose.yaw_rad))
        travel = float(np.arctan2(*(aim - here)[::-1]))
        return self._fly(vehicle, aim, travel, Mode.BACKTRACKING, None)

    def _route_stalled(self, route: _Route, stamp_s: float) -> bool:
        """No progress towards the route's target for ``route_timeout_s``. Progress is a
        waypoint reached, or a route to the same target shorter than any before it: skipping
        ahead along a corridor, the vehicle passes waypoints without slowing at them (in a
        1.5 m wide spiral, a target 70 keyframes back failed twice after 30 s of steady flight)."""
        hops = len(route.keyframes)
        if self._progress_target != route.target_keyframe or hops < self._progress_hops:
            self._progress_target, self._progress_s, self._progress_hops = route.target_keyframe, stamp_s, hops
            return False
        return stamp_s - self._progress_s > self.params.route_timeout_s

    def _sidestep(self, here: FloatArray, wp: FloatArray, required: float) -> FloatArray | None:
        """A point at least ``sidestep_gain_m`` nearer ``wp`` that a straight line reaches
        through the newest scan's free space, clear of its returns as a leg must be; the one
        nearest ``wp``, None when there is none. It trusts the scan alone: the map's views along
        a narrow corridor may each have drifted a little, and together leave no way through."""
        if self._live_view is None or self._live.shape[0] == 0:
            return None
        p = self.params
        dist = float(np.hypot(*(wp - here)))
        bearing = float(np.arctan2(*(wp - here)[::-1]))
        turns = np.deg2rad(np.arange(-p.sidestep_max_deg, p.sidestep_max_deg + 1e-9, p.sidestep_step_deg))
        lengths = np.array([m for m in p.sidestep_lengths_m if m <= dist + p.goal_reached_m])
        if lengths.size == 0:
            return None
        angle = bearing + np.repeat(turns, lengths.size)
        length = np.tile(lengths, turns.size)
        aims = here + np.column_stack((length * np.cos(angle), length * np.sin(angle)))
        gain = dist - np.hypot(*(wp - aims).T)
        ok = gain >= min(p.sidestep_gain_m, 0.5 * dist)
        ok &= self._clear_of_live(here, aims, self._leg_required(required))
        if not ok.any():
            return None
        live = self._live_view()
        idx = np.flatnonzero(ok)
        idx = idx[np.argsort(-gain[idx], kind="stable")]
        lead = here + 0.05 * np.column_stack((np.cos(angle[idx]), np.sin(angle[idx])))
        lines = shapely.linestrings(np.stack((lead, aims[idx]), axis=1))
        inside = shapely.covers(live, lines)
        if not inside.any():
            return None
        return np.asarray(aims[idx[int(np.argmax(inside))]], dtype=np.float64)

    def _approach(
        self, local_map: LocalMap, frame_id: int, view: LocalView, here: FloatArray, min_size_m: float
    ) -> _Candidate | None:
        """A step towards the keyframe's frontier (not set aside) that the free space leads
        nearest to, when that ends at least ``approach_gain_m`` nearer it than ``here``."""
        idx = self._targets(local_map, frame_id, min_size_m)
        reach = self._reach(view, here) if idx else None
        if reach is None:
            return None
        v = local_map.keyframes[frame_id].polygon.vertices_xy[idx]
        cells = reach.nearest_to(v)
        if cells is None:
            return None
        left = np.hypot(*(v - cells).T)
        gain = np.hypot(*(v - here).T) - left
        ok = np.flatnonzero(gain >= self.params.approach_gain_m)
        if ok.size == 0:
            return None
        k = int(ok[np.argmin(left[ok])])
        path = reach.path_to(cells[k])
        if path is None:
            return None
        look = float(np.arctan2(*(v[k] - cells[k])[::-1]))
        return _Candidate(FrontierKey(frame_id, idx[k]), cells[k], look, 0.0, path, approach=True)

    def _leg_points(
        self,
        local_map: LocalMap,
        frame_id: int,
        view: LocalView,
        here: FloatArray,
        keyframe_id: int,
        wp: FloatArray,
        required: float,
    ) -> tuple[FloatArray, bool]:
        """Waypoints to the next route keyframe (at ``wp``), the keyframe last, and whether they
        were planned just now: straight when that is clear, else a path through the view's free
        space (a leg flown once may pass a door jamb the vehicle now sees from elsewhere)."""
        leg = self._leg
        if leg is not None and leg.keyframe_id == keyframe_id:
            pts = local_map.pose_in(frame_id, leg.frame_id).apply(leg.points)
            pts = self._past_corners(pts, here)
            # Flown to its end, yet the keyframe is not there (a loop closure moved it since):
            # plan again from here rather than hold at the end until the route times out.
            stale_end = (
                pts.shape[0] == 1 and not leg.ends_short and self._reached(pts[0], here, self.params.corner_reached_m)
            )
            if not stale_end:
                self._leg = _Leg(frame_id, keyframe_id, pts, ends_short=leg.ends_short, flown=leg.flown)
                return pts, False
        pts = wp[None, :]
        if not self._accessible(view, here, wp, self._leg_required(required)):
            # A leg needs the body radius clear, not the whole margin: a door too narrow for the
            # grid at the full clearance (0.9 m) is still a way out at the leg's.
            for clearance in (self.params.clearance_m, self._leg_clearance()):
                reach = self._reach(view, here, clearance)
                path = None if reach is None else reach.path_to(wp, snap=True)
                if path is not None:
                    pts = path
                    break
        short = float(np.hypot(*(pts[-1] - wp))) > self.params.waypoint_reached_m
        self._leg = _Leg(frame_id, keyframe_id, pts, ends_short=short)
        return pts, True

    def _may_replan(self, frame_id: int, keyframe_id: int, here: FloatArray) -> bool:
        """Whether a leg planned before the newest scan and found blocked once faced may be planned
        again, or counts as blocked: at most ``leg_replans`` times from one spot."""
        r = self._replans
        same = (
            r is not None
            and (r.frame_id, r.keyframe_id) == (frame_id, keyframe_id)
            and math.hypot(float(here[0]) - r.x_m, float(here[1]) - r.y_m) <= self.params.goal_reached_m
        )
        count = r.count + 1 if same and r is not None else 1
        self._replans = _Replans(frame_id, keyframe_id, float(here[0]), float(here[1]), count)
        return count <= self.params.leg_replans

    def _reached(self, point: FloatArray, here: FloatArray, radius_m: float) -> bool:
        """Within ``radius_m`` of a waypoint and slow enough to turn there."""
        return float(np.hypot(*(point - here))) <= radius_m and self._speed_mps <= self.params.corner_speed_mps

    def _fail_keyframe(
        self, local_map: LocalMap, keyframe_id: int, stamp_s: float, size_m: float, at_origin: bool = False
    ) -> None:
        for i in self._targets(local_map, keyframe_id, size_m, aside_too=True):
            self._failed(FrontierKey(keyframe_id, int(i)), stamp_s, at_origin)

    def _targets(
        self,
        local_map: LocalMap,
        keyframe_id: int,
        size_m: float,
        aside_too: bool = False,
        range_limit_only: bool = False,
    ) -> list[int]:
        """A keyframe's open frontier vertices whose runs are at least ``size_m`` long (and at
        least the fragment size), not set aside (unless ``aside_too``); only those at the
        sensor's range limit if asked."""
        kf = local_map.keyframes[keyframe_id]
        idx = self._targetable(local_map, keyframe_id, size_m)
        if range_limit_only:
            idx = idx[kf.polygon.at_range_limit[idx] & walled_runs(kf.kinds)[idx]]
            if idx.size:
                idx = idx[self._openings(local_map, keyframe_id, idx)]
        return [int(i) for i in idx if aside_too or FrontierKey(keyframe_id, int(i)) not in self.set_aside]

    def _openings(self, local_map: LocalMap, keyframe_id: int, idx: NDArray[np.intp]) -> NDArray[np.bool_]:
        """Which of these walled runs' vertices lie in an opening (see ``far_range_limit_fragments``).
        A run whose bracketing vertices have no wall within ``opening_wall_m`` does not: a lone
        return on a wall at the range limit, every other ray missing it (campus seed 7 flew
        27 keyframes back for one by the building's outer wall)."""
        kf = local_map.keyframes[keyframe_id]
        hops = self.params.fragment_reach_hops
        reach = local_map.graph.reached(keyframe_id, hops)
        near = reach.hops <= hops
        walls = [local_map.keyframes[int(k)].walls.reshape(-1, 2) for k in reach.ids[near]]
        if not any(w.shape[0] for w in walls):
            return np.zeros(idx.size, dtype=bool)
        segments = apply_grouped(reach.poses[near], walls).reshape(-1, 2, 2)
        before, after = run_brackets(kf.kinds)
        ends = kf.polygon.vertices_xy[np.concatenate((before[idx], after[idx]))]
        by_end = point_segment_distances(ends, segments) <= self.params.opening_wall_m  # (2K, S)
        k = idx.size
        d = segments[:, 1] - segments[:, 0]
        d /= np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)[:, None]
        mid = segments.mean(axis=1)
        out = np.zeros(k, dtype=bool)
        # Two walls about parallel (walls meeting at a corner bound a pocket), each off the
        # other's line by the opening's width: a gap in one wall at the range limit is as often
        # returns missed on it (a wall 4.97 m off, every other ray returning) as a door. Any wall
        # by each end, not only the nearest: a corridor's end where a side room's wall meets it
        # left a corner's cut face nearest one end (apartment seed 9, in a variant: `complete`
        # at coverage 0.77, its east corridor and three rooms unseen).
        for i in range(k):
            one, other = np.flatnonzero(by_end[i]), np.flatnonzero(by_end[k + i])
            if one.size == 0 or other.size == 0:
                continue
            d1, d2 = d[one][:, None, :], d[other][None, :, :]
            sine = np.abs(d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0])
            gap = mid[other][None, :, :] - mid[one][:, None, :]
            apart = np.abs(d1[..., 0] * gap[..., 1] - d1[..., 1] * gap[..., 0])  # across the first's line
            pair = (sine <= self.params.opening_parallel_sin) & (apart >= self.params.min_frontier_size_m)
            out[i] = bool(pair.any())
        return out

    def _has_targets(
        self, local_map: LocalMap, keyframe_id: int, size_m: float, range_limit_only: bool = False
    ) -> bool:
        if not range_limit_only:  # the common question, asked of every keyframe a route search passes
            if self._targetable(local_map, keyframe_id, size_m).size == 0:
                return False
            if not self.set_aside:
                return True
        return bool(self._targets(local_map, keyframe_id, size_m, range_limit_only=range_limit_only))

    def _targetable(self, local_map: LocalMap, keyframe_id: int, size_m: float) -> NDArray[np.intp]:
        """A keyframe's open frontier vertices whose runs are at least ``size_m`` long and at
        least the fragment size (set-aside ones included; memoised, see targetable_indices)."""
        return targetable_indices(local_map.keyframes[keyframe_id], max(size_m, self.params.fragment_size_m))

    def _has_live_targets(
        self, local_map: LocalMap, keyframe_id: int, size_m: float, range_limit_only: bool = False
    ) -> bool:
        """Open frontiers worth a flight once views along the pose graph are checked too, and
        slivers judged (a stale frontier costs a look, not a flight)."""
        if not self._has_targets(local_map, keyframe_id, size_m, range_limit_only):
            return False
        self._check_through_graph(local_map, keyframe_id)
        targets = np.array(
            self._targets(local_map, keyframe_id, size_m, range_limit_only=range_limit_only), dtype=np.intp
        )
        self._judge_slivers(local_map, keyframe_id, targets)
        return self._has_targets(local_map, keyframe_id, size_m, range_limit_only)

    def _check_through_graph(self, local_map: LocalMap, keyframe_id: int) -> None:
        """Eq. 2.15 for a keyframe's frontiers against the views along the pose graph, once per
        keyframe and map size."""
        now = (len(local_map), local_map.loop_closures)
        before = self._graph_checked.get(keyframe_id)
        if before != now:
            # With no loop closure since the last check, only the views added since can close
            # anything: a new keyframe hangs off the graph by one edge and moves no old path.
            since = before[0] if before is not None and before[1] == now[1] else 0
            if since == 0:  # a walk of the whole graph: within the step's budget
                if self._fresh_checks_left <= 0:
                    return
                self._fresh_checks_left -= 1
            self._graph_checked[keyframe_id] = now
            local_map.close_through_graph(keyframe_id, since_id=since)

    def _find_route(
        self, local_map: LocalMap, frame_id: int, target_id: int | None = None, size_m: float | None = None
    ) -> _Route | None:
        """Fewest-hop route to ``target_id`` (default: the nearest keyframe with open frontiers,
        fragments only when no longer run is left) that avoids the legs seen blocked; None when
        there is none."""
        if target_id is not None:
            size = self.params.min_frontier_size_m if size_m is None else size_m
            return self._route_to(local_map, frame_id, target_id, size)
        p = self.params
        route = self._find_route_for(local_map, frame_id, p.min_frontier_size_m)
        if route is None and p.fragment_size_m < p.min_frontier_size_m:
            route = self._find_route_for(local_map, frame_id, p.fragment_size_m, p.fragment_reach_m)
            if route is None and p.far_range_limit_fragments:
                route = self._find_route_for(local_map, frame_id, p.fragment_size_m, range_limit_only=True)
        return route

    def _find_route_for(
        self,
        local_map: LocalMap,
        frame_id: int,
        size_m: float,
        reach_m: float | None = None,
        range_limit_only: bool = False,
    ) -> _Route | None:
        """:meth:`_find_route` to the nearest keyframe with runs at least ``size_m`` long (and,
        if given, its origin within ``reach_m`` of the current keyframe's, as the graph places it;
        and, if asked, vertices at the sensor's range limit among them)."""
        # Nearest first: each candidate is checked through the graph before a route is planned to
        # it (a stale frontier closed there costs a look, not a flight); the ones beyond the
        # first reachable target wait until they are the nearest.
        # Keyframes tried in vain (from their origins, or with no route left) go last, oldest try
        # first: the next try should come after the others (a blocked goal's cooldown over), not
        # at once from the same spot. With only the last one put last, the route went back and
        # forth between two keyframes taken on one spot by a door, each tried in vain, for 30 s
        # (apartment seed 1): each try counts once per cooldown, so neither was set aside.
        order = [k for k in local_map.graph.order_from(frame_id) if k not in self._tried_in_vain]
        order += sorted(
            (k for k in self._tried_in_vain if k in local_map.keyframes), key=lambda k: self._tried_in_vain[k]
        )
        if reach_m is not None:
            near = self._keyframes_within(local_map, frame_id, reach_m)
            order = [k for k in order if k in near]
        targets = False
        for k in order:
            if not self._has_live_targets(local_map, k, size_m, range_limit_only):
                continue
            targets = True
            route = self._route_to(local_map, frame_id, k, size_m)
            if route is not None:
                return route
        if targets and self.blocked_legs:
            # Frontiers are left but every route to them crosses a leg once seen blocked (on a
            # pose graph without loop closures every route back shares the first leg): those
            # sightings may have been drift or a passing scan artefact (or taken from a bad spot,
            # such as a doorway), so forget them and try again. The sighting that blocked the
            # last route already counted a failed try for its target, which bounds the retries;
            # counting another here would set a target aside for one sighting.
            self.blocked_legs.clear()
            return self._find_route_for(local_map, frame_id, size_m, reach_m, range_limit_only)
        return None

    def _keyframes_within(self, local_map: LocalMap, frame_id: int, reach_m: float) -> set[int]:
        """Keyframes whose origins the graph places within ``reach_m`` of ``frame_id``'s, along
        chains of at most ``fragment_reach_hops``."""
        hops = self.params.fragment_reach_hops
        reach = local_map.graph.reached(frame_id, hops)
        near = (reach.hops <= hops) & (np.hypot(reach.poses[:, 0], reach.poses[:, 1]) <= reach_m)
        return {int(k) for k in reach.ids[near]}

    def _route_to(self, local_map: LocalMap, frame_id: int, target_id: int, size_m: float) -> _Route | None:
        try:
            path = local_map.graph.path(frame_id, target_id, avoid=self.blocked_legs)
        except GraphError:
            return None
        return _Route(path[1:] if len(path) > 1 else path, target_id, size_m)

    # -- output ---------------------------------------------------------------------------------

    def _fly(
        self,
        vehicle: Pose2,
        goal_xy: FloatArray,
        look_rad: float,
        mode: Mode,
        key: FrontierKey | None,
    ) -> Decision:
        """Turn towards the goal before moving, so the sensor sees the path it flies; and brake
        first when moving fast in another direction, so momentum does not carry the vehicle off
        the checked path (it would slide sideways through the turn)."""
        delta = goal_xy - np.array([vehicle.x_m, vehicle.y_m])
        dist = float(np.hypot(*delta))
        if dist <= self.params.goal_reached_m:
            return Decision(mode, Target(float(goal_xy[0]), float(goal_xy[1]), look_rad), key)
        travel = float(np.arctan2(delta[1], delta[0]))
        moving = float(np.arctan2(self._velocity[1], self._velocity[0]))
        sliding = self._speed_mps > self.params.corner_speed_mps and (
            abs(wrap_angle(travel - moving)) > self._turn_first_rad
        )
        if sliding or abs(wrap_angle(travel - vehicle.yaw_rad)) > self._turn_first_rad:
            return Decision(mode, Target(vehicle.x_m, vehicle.y_m, travel), key)
        return Decision(mode, Target(float(goal_xy[0]), float(goal_xy[1]), travel), key)


def _segment_clearances(a: FloatArray, ends: FloatArray, points_xy: FloatArray) -> FloatArray:
    """For each segment from ``a`` to one of the ends (K, 2), its smallest distance to the points."""
    segments = np.stack((np.broadcast_to(a, ends.shape), ends), axis=1)
    return np.asarray(point_segment_distances(points_xy, segments).min(axis=0), dtype=np.float64)


def _segment_clearance(a: FloatArray, b: FloatArray, points_xy: FloatArray) -> float:
    """Smallest distance from the segment a-b to any of the points."""
    return float(_segment_clearances(a, b.reshape(1, 2), points_xy)[0])
