"""The exploration loop, written once: odometry and scans in, a position + yaw setpoint out.

The in-process simulator, the MAVLink link and the Zenoh link all drive this same object. It owns
the local-polygon map and the planner, decides when a scan becomes a keyframe, keeps the vehicle
localised against one keyframe (the *current* keyframe, whose pose in the odometry frame is the
*anchor*), and turns loop closures reported by a SLAM back end into pose-graph edges.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.errors import CoreError
from companion.core.fov_polygon import (
    KIND_FRONTIER,
    FovPolygon,
    PolygonParams,
    behind_scanned_surface,
    on_scanned_surface,
    returns_xy,
    scan_to_polygon,
    seen_past,
)
from companion.core.geometry import FloatArray, Pose2, wrap_angle
from companion.core.local_map import LocalMap, MapParams
from companion.core.loop_closing import FoundClosure, LoopClosingParams, ViewMatcher
from companion.core.messages import DepthScan, LoopClosure, Odometry, Setpoint
from companion.core.obstacle_memory import MemoryAlignParams, RecentReturns
from companion.core.odometry_matching import OdometryMatchingParams, match_odometry_edge
from companion.core.planner import Decision, FrontierPlanner, Mode, PlannerParams, Target
from companion.core.setpoint_lead import LeadParams, LookHold, limit_lead_facing_memory


@dataclass(frozen=True, slots=True)
class ExplorerParams:
    polygon: PolygonParams = field(default_factory=PolygonParams)
    map: MapParams = field(default_factory=MapParams)
    planner: PlannerParams = field(default_factory=PlannerParams)
    # Before the first frontier is chosen, the vehicle turns this far in place at its start
    # (taking views as it turns): a narrow sensor sees a wedge of its surroundings, and what
    # lies behind and beside the start borders no view's frontier. Started facing a wall 0.6 m
    # away the first view had no frontier at all and the run ended `complete` at once (coverage
    # 0.004); started at the end of a long thin room it never looked behind itself (0.935).
    look_around_rad: float = 2.0 * math.pi
    look_around_max_s: float = 20.0  # an autopilot that does not turn the vehicle: go on anyway
    keyframe_distance_m: float = 1.0
    keyframe_angle_rad: float = 0.5
    # A scan between keyframes that sees this far past an open side or shadow frontier vertex of
    # the current view (along the ray through it, at least ``seen_past_fov_margin_rad`` inside
    # its field of view) is taken as a keyframe too, once the vehicle is ``seen_past_min_m`` or
    # ``seen_past_min_rad`` from the last one; flying back, never. Otherwise what the scans
    # between keyframes saw is lost to the map, and the vehicle flew back for such vertices
    # after coverage was full (spiral seed 8: two vertices at the first turn, 142 keyframes
    # back, 144 s after coverage 0.99; such scans, turning the corner, had seen past them).
    # At 0.5 m past, and from 0.2 m or 0.15 rad on, a view was taken almost every step among a
    # forest's trees (three times the keyframes, +25 % time). 0 turns it off.
    seen_past_depth_m: float = 1.0
    seen_past_min_m: float = 0.5
    seen_past_min_rad: float = 0.25
    seen_past_fov_margin_rad: float = 0.05
    backtrack_keyframe_distance_m: float = 3.0  # fewer new views while flying through known space
    # Scans are taken to this range at most (:meth:`DepthScan.capped`): a view's polygon keeps a
    # vertex spacing along its range arc, so its size, and a step's time, grow with the range
    # (the slowest step of an open view: 6 ms at 20 m, 22 ms at 100 m, 0.7 s at 655 m, the largest
    # OBSTACLE_DISTANCE can say; 20 s in one step at 10 km).
    max_scan_range_m: float = 20.0
    flown_spacing_m: float = 0.5  # the way flown between keyframes is kept at this spacing
    loop_closure_max_gap_s: float = 5.0  # a loop closure needs a keyframe this close in time
    velocity_window_s: float = 0.2  # odometry differenced over this long for the vehicle's velocity
    # Take the estimator's velocity when the odometry carries one (else difference the pose).
    # Off without a SLAM back end: that mode's lead and goal choice were tuned on the differenced
    # velocity, and with the steadier one a run crashed (lshape seed 5, session 37).
    use_reported_velocity: bool = True
    # Obstacle returns of recent scans stay in the setpoint's lead limit: a door jamb that has
    # left the sensor's field of view beside the vehicle still stops it short of contact. They
    # are kept for this far of travel (odometry drifts with distance) and this long (people
    # move), until the newest scan's field of view takes them in: there the sensor is the
    # authority (it sees through them, or the surface again, or hides them behind a nearer
    # return). So hovering keeps what lies beside the vehicle: with a 5 s limit a vehicle that
    # hovered 0.4 m from a thin wall's end, out of view, forgot it and turned onto it (longhall
    # seeds 2 and 3). 0 s keeps the newest scan's only.
    # (Planning keeps to the newest scan: remembered returns, a little off after travel, closed
    # narrow doors to the free-space grid and ended office runs early.)
    # Flying back through known space, a loop closure this fresh relocalises the vehicle at the
    # old place it recognised (see Explorer._relocalize).
    relocalize_on_loop_closure: bool = True
    relocalize_max_age_s: float = 1.0
    # A scan stamped after the newest odometry waits (up to this long ahead of it) for odometry
    # that reaches its stamp: placed by an older pose, a scan's polygon is off by the motion
    # since, and a turn swings its far end by metres (one 0.1 s lag tripled a room's time).
    scan_odometry_wait_s: float = 0.5
    obstacle_memory_s: float = 60.0
    obstacle_memory_m: float = 1.5
    # How well a remembered return is known (drift since): one the newest scan sees through
    # within this of its field of view's edge stays remembered. Its wall's end may lie just
    # outside, where no ray passes: forgotten, the vehicle turned round a wall's end into it
    # (apartment seed 4, in a variant). Returns the scan sees as surface go as before.
    obstacle_memory_margin_m: float = 0.1
    # Each scan first aligns the remembered returns to its walls (see companion.core.obstacle_memory).
    obstacle_memory_align: MemoryAlignParams = field(default_factory=MemoryAlignParams)
    # A vehicle on its way (a goal not reached, a route) that stays within ``stall_radius_m`` for
    # ``stall_s`` is held by something the plan does not see (the lead's remembered returns,
    # say): its leg or goal counts as blocked, as when the sensor sees it so. The lead stopped
    # the vehicle by a remembered return beside its leg; turned to look, it was off the leg, and
    # turned back: it rocked between the two until the route timed out (30 s, a generated map).
    # ``LeadParams.rock_turns`` now breaks that rocking; this is the backstop for what else holds it.
    stall_s: float = 8.0
    stall_radius_m: float = 0.2
    lead: LeadParams = field(default_factory=LeadParams)  # how far setpoints may lead the vehicle
    # Loop closures of the companion's own, by matching each new view to old ones (for links
    # that bring none: MAVLink has no loop-closure message).
    loop_closing: LoopClosingParams = field(default_factory=LoopClosingParams)
    # Each odometry edge corrected by matching the new view's walls to its parent's.
    odometry_matching: OdometryMatchingParams = field(default_factory=OdometryMatchingParams)


@dataclass(frozen=True, slots=True)
class StepResult:
    setpoint: Setpoint
    mode: Mode
    keyframe_added: bool
    decision: Decision


class OdometryHistory:
    """Odometry samples by stamp, to find the estimate at a scan's or a loop closure's stamp."""

    def __init__(self) -> None:
        self._stamps: list[float] = []
        self._poses: list[Pose2] = []

    def append(self, odom: Odometry) -> None:
        if self._stamps and odom.stamp_s <= self._stamps[-1]:
            if odom.stamp_s == self._stamps[-1]:
                self._poses[-1] = odom.pose
            return
        self._stamps.append(odom.stamp_s)
        self._poses.append(odom.pose)

    def at(self, stamp_s: float) -> Pose2 | None:
        """Linear interpolation between neighbouring samples; None outside the history."""
        if not self._stamps or stamp_s < self._stamps[0] - 1e-6 or stamp_s > self._stamps[-1] + 1e-6:
            return None
        i = bisect.bisect_left(self._stamps, stamp_s)
        if i < len(self._stamps) and abs(self._stamps[i] - stamp_s) < 1e-9:
            return self._poses[i]
        if i == 0:
            return self._poses[0]
        if i >= len(self._stamps):
            return self._poses[-1]
        t0, t1 = self._stamps[i - 1], self._stamps[i]
        a, b = self._poses[i - 1], self._poses[i]
        w = (stamp_s - t0) / (t1 - t0)
        return Pose2(
            a.x_m + w * (b.x_m - a.x_m),
            a.y_m + w * (b.y_m - a.y_m),
            wrap_angle(a.yaw_rad + w * wrap_angle(b.yaw_rad - a.yaw_rad)),
        )

    def newest_stamp(self) -> float | None:
        return self._stamps[-1] if self._stamps else None

    def between(self, start_s: float, end_s: float) -> list[Pose2]:
        """The samples stamped after ``start_s`` and before ``end_s``."""
        lo = bisect.bisect_right(self._stamps, start_s)
        hi = bisect.bisect_left(self._stamps, end_s)
        return self._poses[lo:hi]

    def shift(self, correction: Pose2) -> None:
        """Re-express the history after an estimator reset (``new = correction ∘ old``)."""
        self._poses = [correction.compose(p) for p in self._poses]


class Explorer:
    """Map + planner behind one call: :meth:`step`."""

    def __init__(self, params: ExplorerParams | None = None) -> None:
        self.params = params or ExplorerParams()
        self.map = LocalMap(self.params.map)
        self.planner = FrontierPlanner(self.params.planner)
        self.current_id: int | None = None
        self.anchor = Pose2.identity()  # current keyframe's pose in the odometry frame
        self._anchor_stamp_s: float | None = None  # when the vehicle was last at the anchor
        self.history = OdometryHistory()
        self.loop_closures_rejected = 0
        self.relocalized = 0  # times a loop closure relocalised the vehicle (see _relocalize)
        self.looks_at_remembered = 0  # steps the vehicle faced a remembered return that held it
        self._want_keyframe = False
        # (frame, map size, loop closures) -> the view's open side and shadow vertices (_sees_past_open)
        self._open_memo: tuple[tuple[int, int, int], FloatArray, list[tuple[int, int]]] | None = None
        self._need_keyframe = False  # a loop closure found no keyframe near its moment (see there)
        self._last_odom: Odometry | None = None
        self._last_mode = Mode.EXPLORING
        self._pending_closures: list[LoopClosure] = []
        self._view_matcher = ViewMatcher(self.params.loop_closing)
        self._matched: FoundClosure | None = None  # found by the matcher, joined to the graph next step
        self.loop_closures_matched = 0  # loop closures found by matching views (see loop_closing)
        self.odometry_edges_matched = 0  # odometry edges corrected by matching (see odometry_matching)
        self._live: tuple[Pose2, FloatArray, DepthScan] | None = None  # newest scan: pose, returns, scan
        self._newest_view_memo: tuple[DepthScan, shapely.Geometry] | None = None  # see _newest_view
        self._recent = RecentReturns(
            self.params.obstacle_memory_s,
            self.params.obstacle_memory_m,
            self.params.obstacle_memory_margin_m,
            self.params.obstacle_memory_align,
        )
        self._travelled_m = 0.0  # odometry path length, to age the recent returns by
        self._obstacles_xy: FloatArray = np.zeros((0, 2))  # recent returns for this step, odometry frame
        self._obstacle_sigmas_m: FloatArray = np.zeros(0)  # how far off each may lie (see RecentReturns)
        self._keyframe_stamps: tuple[list[float], list[int]] = ([], [])  # sorted by stamp, for closures
        self._waiting_scan: DepthScan | None = None  # newer than the odometry so far (see step)
        self._looked_around_rad = 0.0  # turned in place at the start so far (see look_around_rad)
        self._looked_around = self.params.look_around_rad <= 0.0
        self._look_from: tuple[float, Pose2] | None = None  # when and where it began (odometry frame)
        self._still_since: tuple[float, Pose2] | None = None  # on its way, standing here since (see stall_s)
        self.stalls = 0  # legs and goals taken as blocked because the vehicle stood still on them
        self._look_hold = LookHold(self.params.lead)  # facing a remembered return through rocking

    @property
    def mode(self) -> Mode:
        return self._last_mode

    def step(self, odom: Odometry, scan: DepthScan | None = None) -> StepResult:
        """Take the newest odometry (and a scan, if one arrived) and return the next setpoint."""
        if not (odom.pose.is_finite() and math.isfinite(odom.stamp_s)):
            raise CoreError("odometry must be finite")
        last = self._last_odom
        if last is not None and odom.reset_counter == last.reset_counter:  # a reset is no travel
            self._travelled_m += last.pose.distance_to(odom.pose)
        self._handle_reset(odom)
        self.history.append(odom)
        self._last_odom = odom
        if scan is not None:
            scan = scan.capped(self.params.max_scan_range_m)
        scan = self._scan_with_odometry(scan)
        added = False
        if scan is not None:
            returns = returns_xy(scan, self.params.polygon.frontier_range_tolerance_m)
            pose_at_scan = self.history.at(scan.stamp_s) or odom.pose
            self._live = (pose_at_scan, returns, scan)
            self._recent.align(scan, pose_at_scan, self._travelled_m, self.params.polygon.frontier_range_tolerance_m)
            self._recent.add(scan.stamp_s, self._travelled_m, pose_at_scan.apply(returns))
            if self.current_id is None:  # the first view: there is nothing to plan on before it
                added = self._maybe_add_keyframe(scan, odom)
        if self.current_id is None:
            hold = Setpoint(odom.pose.x_m, odom.pose.y_m, odom.pose.yaw_rad)
            decision = Decision(Mode.EXPLORING, Target(hold.x_m, hold.y_m, hold.yaw_rad))
            return StepResult(hold, Mode.EXPLORING, added, decision)
        looking_around = self._looking_around(odom, last)
        vehicle = self.anchor.between(odom.pose)
        live = None
        live_view: Callable[[], shapely.Geometry] | None = None
        live_surface: Callable[[FloatArray, float], NDArray[np.bool_]] | None = None
        live_hidden: Callable[[FloatArray, float], NDArray[np.bool_]] | None = None
        if self._live is not None:
            pose_at_scan, returns, newest = self._live
            scan_pose = self.anchor.between(pose_at_scan)
            self._obstacles_xy = self._recent_obstacles(pose_at_scan, newest)
            live = scan_pose.apply(returns)

            def live_view() -> shapely.Geometry:  # only built when the planner needs it
                return scan_pose.move(self._newest_view(newest))

            def live_surface(points_xy: FloatArray, tol_m: float) -> NDArray[np.bool_]:
                margin = self.params.polygon.frontier_range_tolerance_m
                return on_scanned_surface(newest, scan_pose, points_xy, tol_m, margin)

            def live_hidden(points_xy: FloatArray, depth_m: float) -> NDArray[np.bool_]:
                margin = self.params.polygon.frontier_range_tolerance_m
                return behind_scanned_surface(newest, scan_pose, points_xy, depth_m, margin)

        velocity = self._velocity_in_frame(odom)
        if looking_around:
            decision = self._look_around(odom)
        else:
            self._watch_stall(odom)
            half_fov = None if self._live is None else _half_fov_rad(self._live[2])
            decision = self.planner.plan(
                self.map,
                self.current_id,
                vehicle,
                odom.stamp_s,
                live,
                velocity,
                live_view,
                live_surface,
                half_fov,
                live_hidden=live_hidden,
            )
        t = decision.target  # in the current keyframe's frame, before any relocalisation
        x, y = self.anchor.apply_point(t.x_m, t.y_m)
        sp = Setpoint(x, y, wrap_angle(t.yaw_rad + self.anchor.yaw_rad))
        if decision.relocalize_to is not None and decision.relocalize_to != self.current_id:
            rel = self.map.pose_in(self.current_id, decision.relocalize_to)
            self.anchor = self.anchor.compose(rel)
            self.current_id = decision.relocalize_to
            self._anchor_stamp_s = odom.stamp_s
        if decision.want_keyframe:
            self._want_keyframe = True
        sp = self._within_lead(sp, odom.pose, velocity, odom.stamp_s)
        self._last_mode = decision.mode
        # Then at most one change to the map, which the next step plans on: a due keyframe, else
        # the queued loop closures. Each costs several milliseconds, and so does planning on a
        # changed map; spread over two steps, no step holds the control loop up for all of it.
        if not added:
            if scan is not None and self._maybe_add_keyframe(scan, odom):
                added = True
            elif self._matched is not None:
                self._add_matched()
            elif self._view_matcher.busy:
                self._match_views()
            elif self._pending_closures:
                self._apply_pending_closures()
        return StepResult(sp, decision.mode, added, decision)

    def _looking_around(self, odom: Odometry, last: Odometry | None) -> bool:
        """Still turning in place at the start (see ``look_around_rad``)? Counts the turn made
        (signed: it turns one way, and a hovering estimate's jitter cancels out); once done,
        never again."""
        p = self.params
        if self._looked_around:
            return False
        if self._look_from is None:
            self._look_from = (odom.stamp_s, odom.pose)
        elif last is not None and odom.reset_counter == last.reset_counter:
            self._looked_around_rad += wrap_angle(odom.pose.yaw_rad - last.pose.yaw_rad)
        timed_out = odom.stamp_s - self._look_from[0] >= p.look_around_max_s
        self._looked_around = self._looked_around_rad >= p.look_around_rad or timed_out
        return not self._looked_around

    def _look_around(self, odom: Odometry) -> Decision:
        """The turn in place at the start, in place of the planner's decision: the start's
        position, the heading a quarter turn ahead (views are taken as it changes)."""
        assert self._look_from is not None
        start = self._look_from[1]
        turn = self.anchor.between(Pose2(start.x_m, start.y_m, odom.pose.yaw_rad + 0.5 * math.pi))
        return Decision(Mode.EXPLORING, Target(turn.x_m, turn.y_m, turn.yaw_rad))

    @property
    def obstacles_xy(self) -> FloatArray:
        """The obstacle returns the setpoint's lead limit used in the last step (odometry frame):
        the recent scans' (:class:`RecentReturns`), less those the newest scan sees through."""
        return self._obstacles_xy

    def map_counts(self) -> dict[str, int]:
        """The map and frontier figures every report carries (the simulator's and the service's)."""
        return {
            "keyframes": len(self.map),
            "loop_closures": self.map.loop_closures,
            "loop_closures_matched": self.loop_closures_matched,
            "odometry_edges_matched": self.odometry_edges_matched,
            "frontiers_left": self.map.open_frontier_count(),
            "frontiers_set_aside": len(self.planner.unreachable(self.map)),
            "frontiers_closed_on_sight": self.planner.closed_on_sight,
            "frontiers_closed_on_surface": self.planner.closed_on_surface,
            "frontiers_closed_as_slivers": self.map.slivers_closed,
            "steps_looking_at_remembered": self.looks_at_remembered,
            "stalls": self.stalls,
        }

    def add_loop_closure(self, closure: LoopClosure) -> None:
        """Queue a SLAM loop closure: a step joins it to the graph once odometry covers both its
        moments (after that step's plan, and not in a step that adds a keyframe)."""
        self._pending_closures.append(closure)

    def _apply_pending_closures(self) -> None:
        newest = self.history.newest_stamp()
        keep: list[LoopClosure] = []
        for closure in self._pending_closures:
            if newest is not None and closure.current_stamp_s <= newest + 1e-6:
                self._apply_loop_closure(closure)
            elif newest is None or closure.current_stamp_s - newest < self.params.loop_closure_max_gap_s:
                keep.append(closure)
            else:
                self.loop_closures_rejected += 1
        self._pending_closures = keep

    def _apply_loop_closure(self, closure: LoopClosure) -> bool:
        """Turn a loop closure into a pose-graph edge between keyframes near its two moments: the
        nearest in time whose view holds where the vehicle was at that moment (so the edge joins
        places that see each other, not two sides of a wall the vehicle had just flown round),
        else the nearest in time.

        Returns False (and counts it) when no keyframe is close enough in time to either moment
        or the odometry at those moments is not known.
        """
        gap = self.params.loop_closure_max_gap_s
        pe = self.history.at(closure.earlier_stamp_s)
        pc = self.history.at(closure.current_stamp_s)
        if pe is None or pc is None or not closure.earlier_to_current.is_finite():
            self.loop_closures_rejected += 1
            return False
        a = self._keyframe_near(closure.earlier_stamp_s, pe, gap)
        b = self._keyframe_near(closure.current_stamp_s, pc, gap)
        if a is None or b is None or a == b:
            if a is not None and b is None and self._last_mode is Mode.BACKTRACKING:
                # Stalled on a route, the vehicle takes no view, so no closure finds a keyframe
                # near its moment and none relocalises it: take one now for the next.
                self._need_keyframe = True
            self.loop_closures_rejected += 1
            return False
        current_in_a = self.map.keyframes[a].odom_pose.between(pe).compose(closure.earlier_to_current)
        a_to_b = current_in_a.compose(pc.between(self.map.keyframes[b].odom_pose))
        if a < b:
            self.map.add_loop_closure(a, b, a_to_b)
        else:
            self.map.add_loop_closure(b, a, a_to_b.inverse())
        self._relocalize(a, current_in_a, closure.current_stamp_s)
        return True

    def _relocalize(self, keyframe_id: int, current_in_keyframe: Pose2, stamp_s: float) -> None:
        """While flying back through known space, take a fresh loop closure's measured pose as
        where the vehicle is: its frame becomes the old place's keyframe. Otherwise the vehicle
        knows where it is along the route only by odometry since the last keyframe it took and by
        the route keyframes it believes it reached, and that error grows with every metre flown
        back (the thesis teleported the vehicle there instead)."""
        newest = self.history.newest_stamp()
        pose_then = self.history.at(stamp_s)
        if (
            not self.params.relocalize_on_loop_closure
            or self._last_mode is not Mode.BACKTRACKING
            or newest is None
            or pose_then is None
            or newest - stamp_s > self.params.relocalize_max_age_s
        ):
            return
        now = self.history.at(newest)
        assert now is not None
        vehicle = current_in_keyframe.compose(pose_then.between(now))
        if not self._in_sight(keyframe_id, vehicle, now):
            return
        self.anchor = now.compose(vehicle.inverse())
        self.current_id = keyframe_id
        self._anchor_stamp_s = newest
        self.relocalized += 1

    def _in_sight(self, keyframe_id: int, vehicle: Pose2, now: Pose2) -> bool:
        """Whether the old place and the vehicle (at ``vehicle`` in its frame, ``now`` by odometry)
        see each other: the place's view holds the vehicle, or the newest scan's holds the place.
        The keyframe a loop closure joins is the one nearest its moment in time, up to seconds of
        flight from the place recognised, and may lie out of sight (in the hall, across the wall of
        the room the vehicle is in): taken as the vehicle's frame, the next keyframe would hang off
        the graph by a leg through that wall, and every route out be blocked (longhall seed 9
        ended at coverage 0.55)."""
        if self.map.keyframes[keyframe_id].polygon.shape.dwithin(shapely.Point(vehicle.x_m, vehicle.y_m), 0.05):
            return True
        if self._live is None:
            return False
        pose_at_scan, _, newest = self._live
        place = vehicle.compose(now.between(pose_at_scan)).inverse()  # the place in the scan's frame
        return bool(self._newest_view(newest).dwithin(shapely.Point(place.x_m, place.y_m), 0.05))

    def _newest_view(self, scan: DepthScan) -> shapely.Geometry:
        """The newest scan's field-of-view polygon in its own frame, built once per scan."""
        if self._newest_view_memo is None or self._newest_view_memo[0] is not scan:
            self._newest_view_memo = (scan, scan_to_polygon(scan, self.params.polygon).shape)
        return self._newest_view_memo[1]

    # -- internals -------------------------------------------------------------------------------

    def _scan_with_odometry(self, scan: DepthScan | None) -> DepthScan | None:
        """The newest scan the odometry so far reaches (its pose at the scan's stamp is known);
        a newer one waits for a later step. One too far ahead of the odometry (another clock,
        or odometry that stalled) is taken with the newest pose rather than held for ever."""
        newest = self.history.newest_stamp()
        assert newest is not None
        ready: DepthScan | None = None
        for s in (self._waiting_scan, scan):
            if s is None:
                continue
            ahead_s = s.stamp_s - newest
            if ahead_s <= 1e-6 or ahead_s > self.params.scan_odometry_wait_s:
                ready = s
                self._waiting_scan = None
            else:
                self._waiting_scan = s
        return ready

    def _handle_reset(self, odom: Odometry) -> None:
        last = self._last_odom
        if last is None or odom.reset_counter == last.reset_counter:
            return
        # The estimator jumped; assume no motion across the jump and carry the anchor over.
        correction = odom.pose.compose(last.pose.inverse())
        self.anchor = correction.compose(self.anchor)
        self.history.shift(correction)
        self._recent.shift(correction)
        # The keyframes' estimates too: a loop closure to a place seen before the jump pairs
        # the keyframe's estimate with the (shifted) history, and would carry the jump.
        for kf in self.map.keyframes.values():
            kf.odom_pose = correction.compose(kf.odom_pose)

    def _velocity_in_frame(self, odom: Odometry) -> tuple[float, float]:
        """The vehicle's velocity in the current keyframe's frame: the estimator's own when the
        odometry carries one (finite), else the pose differenced over ``velocity_window_s``."""
        reported = odom.velocity_xy
        if self.params.use_reported_velocity and reported is not None and all(map(math.isfinite, reported)):
            vx, vy = reported
        else:
            before = self.history.at(odom.stamp_s - self.params.velocity_window_s)
            if before is None:
                return (0.0, 0.0)
            dt = self.params.velocity_window_s
            vx, vy = (odom.pose.x_m - before.x_m) / dt, (odom.pose.y_m - before.y_m) / dt
        c, s = math.cos(self.anchor.yaw_rad), math.sin(self.anchor.yaw_rad)
        return (c * vx + s * vy, -s * vx + c * vy)

    def _watch_stall(self, odom: Odometry) -> None:
        """Tell the planner when the vehicle has stood still on its way for ``stall_s``."""
        if not self.planner.pursuing or self.params.stall_s <= 0.0:
            self._still_since = None
            return
        since = self._still_since
        if since is None or since[1].distance_to(odom.pose) > self.params.stall_radius_m:
            self._still_since = (odom.stamp_s, odom.pose)
        elif odom.stamp_s - since[0] >= self.params.stall_s:
            self.planner.note_stall()
            self.stalls += 1
            self._still_since = (odom.stamp_s, odom.pose)

    def _within_lead(
        self, sp: Setpoint, pose: Pose2, velocity_in_frame: tuple[float, float], stamp_s: float
    ) -> Setpoint:
        """The setpoint limited to the lead (see :mod:`setpoint_lead`), all in the odometry frame:
        the newest scan's returns, and the earlier ones remembered. Held by remembered returns
        alone, the vehicle faces the one in its way, so the sensor sees whether it is still there
        (and goes on facing it once it has rocked between it and its way: ``LeadParams.rock_turns``)."""
        returns = self._obstacles_xy
        split = returns.shape[0] - self._recent.newest_count()
        newest, remembered = returns[split:], returns[:split]
        vx, vy = self.anchor.rotate(np.array([velocity_in_frame]))[0]
        radius = self.params.planner.body_radius_m
        sigmas = self._obstacle_sigmas_m[:split]
        limited, blocker = limit_lead_facing_memory(
            sp, pose, (float(vx), float(vy)), newest, radius, self.params.lead, remembered, sigmas
        )
        in_place = math.hypot(limited.x_m - pose.x_m, limited.y_m - pose.y_m) <= self.params.planner.goal_reached_m
        limited, blocker = self._look_hold.apply(limited, blocker, pose, remembered, in_place, stamp_s)
        if blocker is not None:
            self.looks_at_remembered += 1
        return limited

    def _recent_obstacles(self, pose_at_scan: Pose2, newest: DepthScan) -> FloatArray:
        """The recent returns (odometry frame), less the earlier scans' inside the newest one's
        view (:meth:`RecentReturns.forget_seen`)."""
        self._recent.forget_seen(newest, pose_at_scan)
        self._obstacle_sigmas_m = self._recent.sigmas_m()
        return self._recent.points_xy()

    def _keyframe_near(self, stamp_s: float, pose: Pose2, gap_s: float) -> int | None:
        """The keyframe nearest in time to ``stamp_s`` (within ``gap_s``) whose view holds
        ``pose``'s position, else the nearest in time. Odometry spans a few seconds here only."""
        stamps, ids = self._keyframe_stamps
        lo = bisect.bisect_left(stamps, stamp_s - gap_s - 1e-6)
        hi = bisect.bisect_right(stamps, stamp_s + gap_s + 1e-6)
        near = sorted((abs(stamps[i] - stamp_s), ids[i]) for i in range(lo, hi))
        near = [(d, k) for d, k in near if d <= gap_s]
        for _, k in near:
            kf = self.map.keyframes[k]
            rel = kf.odom_pose.between(pose)
            if kf.polygon.shape.dwithin(shapely.Point(rel.x_m, rel.y_m), 0.05):  # its origin too
                return k
        return near[0][1] if near else None

    def _flown_xy(self, until_s: float, end: Pose2) -> FloatArray:
        """The way flown from the anchor until ``until_s`` (to ``end``), in the anchor's frame:
        a point every ``flown_spacing_m``, none that close to either end."""
        spacing = self.params.flown_spacing_m
        if self._anchor_stamp_s is None or spacing <= 0.0:
            return np.zeros((0, 2))
        last = np.zeros(2)
        goal = np.array([end.x_m, end.y_m])
        kept: list[FloatArray] = []
        for p in self.history.between(self._anchor_stamp_s, until_s):
            rel = self.anchor.between(p)
            xy = np.array([rel.x_m, rel.y_m])
            if np.hypot(*(xy - last)) >= spacing and np.hypot(*(xy - goal)) >= spacing:
                kept.append(xy)
                last = xy
        return np.array(kept) if kept else np.zeros((0, 2))

    def _maybe_add_keyframe(self, scan: DepthScan, odom: Odometry) -> bool:
        pose = self.history.at(scan.stamp_s) or odom.pose
        p = self.params
        if self.current_id is not None:
            rel = self.anchor.between(pose)
            dist = math.hypot(rel.x_m, rel.y_m)
            turn = abs(rel.yaw_rad)
            backtracking = self._last_mode is Mode.BACKTRACKING
            limit = p.backtrack_keyframe_distance_m if backtracking else p.keyframe_distance_m
            due = dist >= limit or (not backtracking and turn >= p.keyframe_angle_rad)
            if self._want_keyframe and (dist > 0.2 or turn > 0.15):
                due = True
            due = due or self._need_keyframe
            if not due and not backtracking and (dist > p.seen_past_min_m or turn > p.seen_past_min_rad):
                due = self._sees_past_open(scan, rel)
            if not due:
                return False
        polygon = scan_to_polygon(scan, p.polygon)
        if polygon.shape.is_empty:
            return False
        parent, flown = None, None
        if self.current_id is not None:
            guess = self.anchor.between(pose)
            edge = self._odometry_edge(polygon, guess)
            parent = (self.current_id, edge)
            flown = _bent_to(self._flown_xy(scan.stamp_s, guess), guess, edge)
        kf = self.map.add_keyframe(scan.stamp_s, pose, polygon, parent, flown)
        at = bisect.bisect_right(self._keyframe_stamps[0], kf.stamp_s)
        self._keyframe_stamps[0].insert(at, kf.stamp_s)
        self._keyframe_stamps[1].insert(at, kf.keyframe_id)
        self.current_id = kf.keyframe_id
        self.anchor = pose
        self._anchor_stamp_s = scan.stamp_s
        self._want_keyframe = False
        self._need_keyframe = False
        if p.loop_closing.enabled:
            self._view_matcher.start(kf.keyframe_id)
        return True

    def _sees_past_open(self, scan: DepthScan, scan_pose: Pose2) -> bool:
        """The scan (at ``scan_pose`` in the current keyframe's frame) sees at least
        ``seen_past_depth_m`` past an open frontier vertex of the current view that is not at
        its own view's range limit (a side or shadow vertex), along the ray through it, inside
        its field of view."""
        depth = self.params.seen_past_depth_m
        if depth <= 0.0 or self.current_id is None:
            return False
        pts, owners = self._open_side_and_shadow()
        if pts.shape[0] == 0:
            return False
        edge = self.params.seen_past_fov_margin_rad
        past = np.flatnonzero(seen_past(scan, scan_pose, pts, depth, edge, nearest_m=0.3))  # not beside the sensor
        # The list may be a few keyframes old: ask whether each vertex is still open.
        return any(self.map.keyframes[owners[i][0]].kinds[owners[i][1]] == KIND_FRONTIER for i in past)

    def _open_side_and_shadow(self) -> tuple[FloatArray, list[tuple[int, int]]]:
        """The current view's open frontier vertices not at the range limit, in its frame, with
        (keyframe, vertex) of each; kept until the map or the frame changes."""
        assert self.current_id is not None
        key = (self.current_id, len(self.map), self.map.loop_closures)
        if self._open_memo is None or self._open_memo[0] != key:
            view = self.map.view(self.current_id)
            pts: list[FloatArray] = []
            owners: list[tuple[int, int]] = []
            for k, pose in view.poses.items():
                kf = self.map.keyframes[k]
                idx = kf.open_frontier_indices()
                idx = idx[~kf.polygon.at_range_limit[idx]]
                if idx.size:
                    pts.append(pose.apply(kf.polygon.vertices_xy[idx]))
                    owners.extend((k, int(i)) for i in idx)
            self._open_memo = (key, np.vstack(pts) if pts else np.zeros((0, 2)), owners)
        return self._open_memo[1], self._open_memo[2]

    def _odometry_edge(self, polygon: FovPolygon, guess: Pose2) -> Pose2:
        """The new keyframe's pose in the current one's frame: the odometry's ``guess``,
        corrected by matching the new view's walls to the current view's (see odometry_matching)."""
        assert self.current_id is not None
        if not self.params.odometry_matching.enabled:
            return guess
        parent = self.map.keyframes[self.current_id]
        matched = match_odometry_edge(polygon, parent, guess, self.params.odometry_matching)
        if matched is None:
            return guess
        self.odometry_edges_matched += 1
        return matched

    def _match_views(self) -> None:
        """A step of the search for a loop closure of the companion's own (see loop_closing);
        spread over steps, so no step holds the control loop up for all of it."""
        self._matched = self._view_matcher.step(self.map)

    def _add_matched(self) -> None:
        """Join the matched views by a loop-closure edge (a step of its own: the edge's frontier
        closing costs as much as a match)."""
        found = self._matched
        assert found is not None
        self._matched = None
        self.map.add_loop_closure(found.earlier_id, found.later_id, found.earlier_to_later)
        self.loop_closures_matched += 1


def _bent_to(flown_xy: FloatArray, odometry_end: Pose2, matched_end: Pose2) -> FloatArray:
    """The way flown (odometry, ending at ``odometry_end``) bent to end at ``matched_end``
    instead: each point moved by its share (by distance along the way) of the correction."""
    if flown_xy.shape[0] == 0 or matched_end == odometry_end:
        return flown_xy
    correction = matched_end.compose(odometry_end.inverse())
    way = np.vstack(([0.0, 0.0], flown_xy, [odometry_end.x_m, odometry_end.y_m]))
    along = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(way, axis=0).T))))
    share = along[1:-1] / max(float(along[-1]), 1e-9)
    out = np.empty_like(flown_xy)
    for i, (xy, f) in enumerate(zip(flown_xy, share, strict=True)):
        part = Pose2(f * correction.x_m, f * correction.y_m, f * correction.yaw_rad)
        out[i] = part.apply(xy[None])[0]
    return out


def _half_fov_rad(scan: DepthScan) -> float:
    """How far off the sensor's axis a direction stays in the scan's view on both sides (its
    narrower side, for a view not centred on the axis; 0 for one that does not span the axis)."""
    b = scan.bearings_rad
    if b.size == 0:
        return 0.0
    return float(max(0.0, min(-float(b[0]), float(b[-1]))))
