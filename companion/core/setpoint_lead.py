"""How far ahead of the vehicle a position setpoint may lie: the companion's speed limit.

An autopilot flies a far position target as fast as its own limits allow (PX4 offboard up to
MPC_XY_VEL_MAX, 12 m/s by default) and a near one about as fast as its position gain makes of the
distance, braking to stop on it. So the setpoint is kept within a maximum lead of the vehicle, and
within the free travel the newest scan shows towards it: the vehicle comes in slowly enough to stop
short of a seen obstacle, whatever the planner asks next. Moving, the vehicle does not fly the
setpoint's straight line: momentum carries it on while it turns. So the way it would take were the
setpoint to stay put (:func:`stop_path`, a modelled autopilot) must keep the same berth; else the
lead is halved until it does, or the vehicle brakes. That way, not the motion's straight line,
decides: checked along the straight line, a vehicle drifting 5 degrees towards one wall of a 1 m
corridor was held to a crawl, though stopping that drift takes millimetres. Already closer to a
return than the body's plain berth (a tight door), even braking carries the vehicle a little
deeper; there a way no deeper than braking's is allowed (along or away), else it hovered there.

Returns remembered from earlier scans (out of view now) hold the vehicle too, with more berth: the
more, the farther off drift since may have moved each (:mod:`companion.core.obstacle_memory`). When
they alone hold it where the newest scan would let it go, the vehicle turns to look at the one in its
way (:func:`limit_lead_facing_memory`): the sensor then sees it again, or sees through it, and the scan
decides. Forgetting it instead (an age limit) let a vehicle that had hovered beside a thin wall's
end turn onto it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from companion.core.geometry import FloatArray, Pose2, first_contact
from companion.core.messages import Setpoint


@dataclass(frozen=True, slots=True)
class LeadParams:
    """How far setpoints may lead the vehicle; distances in metres."""

    max_lead_m: float = 1.5
    contact_margin_m: float = 0.05  # a return this close to the body (its radius) counts as touched
    # Remembered returns (earlier scans', out of view now) count as touched this much farther
    # out: they sample a surface at the ray spacing (7.5 cm at 3 m), so a jamb's corner lies
    # between two of them, and odometry has moved them a few centimetres since. At the plain
    # margin a vehicle sliding past a corner outside its field of view touched it (longhall
    # seed 2). The newest scan's returns keep the plain margin: it is ahead, where speed is.
    memory_margin_m: float = 0.05
    # And farther by this many standard deviations of how far off each may lie by now: the
    # drift since its scan that aligning the memory to the newest scans could not take out
    # (companion.core.obstacle_memory; along a corridor, or through a door, the walls in view
    # fix nothing along the way).
    memory_sigmas: float = 2.0
    stop_margin_m: float = 0.1  # the setpoint stays this much short of touching
    moving_mps: float = 0.1  # above this speed the motion is checked too (its predicted way or its line)
    # The contact radius grows by this many seconds of speed: at speed the vehicle does not hold
    # a line to the centimetre (a turn, drift, the autopilot's own tracking), and a corner its
    # line passes 0.3 m from at 1.5 m/s is one it may hit; it cannot brake in time once it sees it.
    speed_margin_s: float = 0.15
    # Remembered returns hold the vehicle when they leave it at most this much lead while the
    # newest scan alone would leave it at least ``look_lead_m``: then it looks at what holds it.
    hold_m: float = 0.05
    look_lead_m: float = 0.2
    # Facing one, the vehicle may turn off its way by more than the planner lets it fly without
    # turning first: the next step turns it back, where the return holds it again, and it rocks
    # on one spot (commanded yaw alternating every step). After ``rock_turns`` such turns back
    # within ``rock_window_s`` it goes on facing the return until the sensor takes it in (or it
    # is otherwise forgotten), for at most ``look_hold_s``.
    rock_turns: int = 3
    rock_window_s: float = 1.5
    look_hold_s: float = 2.0
    # The return faced is followed from step to step to the nearest remembered one within this:
    # each scan's alignment moves the memory a few centimetres (companion.core.obstacle_memory),
    # and matched exactly, the return was "gone" the step after each look, so the rocking above
    # was never caught (stalls 0 -> 11 in 450 runs, session 48).
    look_follow_m: float = 0.1
    # Moving, the vehicle does not fly the setpoint's straight line: its momentum carries it on
    # while it turns. The way it would take, were the setpoint to stay put, is predicted with an
    # autopilot that coasts ``model_delay_s`` (the setpoint's trip and a control cycle), then
    # changes its velocity at ``model_accel_mps2`` at most: no more than the autopilot really
    # brakes with (config ``vehicle.braking_accel_mps2``; PX4's MPC_ACC_HOR defaults to 3 m/s2,
    # ArduPilot's WPNAV_ACCEL to 2.5; the simulated vehicle's is 1). That way must keep the berth,
    # sampled every ``model_step_s`` for up to ``model_horizon_s``.
    model_accel_mps2: float = 1.0
    model_delay_s: float = 0.1
    model_step_s: float = 0.05
    model_horizon_s: float = 4.0
    # Off, the motion's straight line is checked instead of the predicted way (the companion's
    # tuning without a SLAM back end: see companion.app.tuning_for).
    predict_way: bool = True


def limit_lead(
    setpoint: Setpoint,
    pose: Pose2,
    velocity_xy: tuple[float, float],
    returns_xy: FloatArray,
    body_radius_m: float,
    params: LeadParams,
    remembered_xy: FloatArray | None = None,
    remembered_sigma_m: FloatArray | None = None,
) -> Setpoint:
    """The setpoint moved along its line from the vehicle to at most the allowed lead (yaw kept).

    ``velocity_xy``, ``returns_xy`` (the newest scan's obstacle points) and ``remembered_xy``
    (earlier scans') are in the setpoint's frame. Already closer to a return than the body
    radius and contact margin (a tight door) the vehicle may move along or away, only not closer
    still. Only returns count, never the map: a drifted view's wall placed on the vehicle must
    not shrink the berth to nothing (office 2 flew into a wall that way). The faster it moves,
    the wider a berth its line must give a return.
    """
    lead, _ = _lead_m(setpoint, pose, velocity_xy, returns_xy, body_radius_m, params, remembered_xy, remembered_sigma_m)
    return _within(setpoint, pose, lead)


def limit_lead_facing_memory(
    setpoint: Setpoint,
    pose: Pose2,
    velocity_xy: tuple[float, float],
    returns_xy: FloatArray,
    body_radius_m: float,
    params: LeadParams,
    remembered_xy: FloatArray,
    remembered_sigma_m: FloatArray | None = None,
) -> tuple[Setpoint, FloatArray | None]:
    """:func:`limit_lead`; but when remembered returns alone hold the vehicle (see
    :class:`LeadParams`), the setpoint faces the one its way touches first, so the sensor sees it
    again. Returns the setpoint and that return (None when nothing remembered holds it)."""
    held, blocker = _lead_m(
        setpoint, pose, velocity_xy, returns_xy, body_radius_m, params, remembered_xy, remembered_sigma_m
    )
    limited = _within(setpoint, pose, held)
    if blocker is None or held > params.hold_m:
        return limited, None
    free, _ = _lead_m(setpoint, pose, velocity_xy, returns_xy, body_radius_m, params, None)
    if free < params.look_lead_m:
        return limited, None
    yaw = math.atan2(float(blocker[1]) - pose.y_m, float(blocker[0]) - pose.x_m)
    return Setpoint(limited.x_m, limited.y_m, yaw), blocker


class LookHold:
    """Keeps the setpoint facing a remembered return once the vehicle rocks between it and its
    way (see ``LeadParams.rock_turns``): what :func:`limit_lead_facing_memory` does step by
    step, remembered across steps."""

    def __init__(self, params: LeadParams) -> None:
        self.params = params
        self._looked_at: tuple[float, FloatArray] | None = None  # the return last faced: when, where
        self._turns_back: list[float] = []  # turns in place away from it, each right after facing it
        self._was_looking = False  # the last step's setpoint faced a remembered return

    def apply(
        self,
        limited: Setpoint,
        blocker: FloatArray | None,
        pose: Pose2,
        remembered_xy: FloatArray,
        in_place: bool,
        stamp_s: float,
    ) -> tuple[Setpoint, FloatArray | None]:
        """This step's setpoint and the remembered return it faces, from
        :func:`limit_lead_facing_memory`'s (``in_place``: the setpoint stays where the vehicle is)."""
        p, looked = self.params, self._looked_at
        if blocker is None and looked is not None:
            near = np.hypot(*(remembered_xy - looked[1]).T) if remembered_xy.shape[0] else np.zeros(0)
            gone = near.size == 0 or float(np.min(near)) > p.look_follow_m
            if gone or not in_place or stamp_s - looked[0] > p.look_hold_s:
                self._looked_at, self._turns_back = None, []
            else:
                looked = self._looked_at = (looked[0], remembered_xy[int(np.argmin(near))])
                recent = [t for t in self._turns_back if stamp_s - t <= p.rock_window_s]
                self._turns_back = [*recent, stamp_s] if self._was_looking else recent
                if len(self._turns_back) >= p.rock_turns:  # rocking: face the return still
                    yaw = math.atan2(float(looked[1][1]) - pose.y_m, float(looked[1][0]) - pose.x_m)
                    limited, blocker = Setpoint(limited.x_m, limited.y_m, yaw), looked[1]
        elif blocker is not None and (looked is None or len(self._turns_back) < p.rock_turns):
            self._looked_at = (stamp_s, blocker)
        self._was_looking = blocker is not None
        return limited, blocker


def _within(setpoint: Setpoint, pose: Pose2, lead_m: float) -> Setpoint:
    """The setpoint moved along its line from the vehicle to at most ``lead_m`` away (yaw kept)."""
    dx, dy = setpoint.x_m - pose.x_m, setpoint.y_m - pose.y_m
    dist = math.hypot(dx, dy)
    if lead_m >= dist:
        return setpoint
    k = lead_m / dist
    return Setpoint(pose.x_m + k * dx, pose.y_m + k * dy, setpoint.yaw_rad)


class _ReturnSet(NamedTuple):
    """One set of returns the lead keeps clear of (the newest scan's, or the remembered ones)."""

    rel_xy: FloatArray  # relative to the vehicle
    contact_m: FloatArray  # the berth the way must keep from each
    remembered: bool
    tight: bool  # the vehicle is already closer to one than the body's plain berth (a tight door)


def _lead_m(
    setpoint: Setpoint,
    pose: Pose2,
    velocity_xy: tuple[float, float],
    returns_xy: FloatArray,
    body_radius_m: float,
    params: LeadParams,
    remembered_xy: FloatArray | None,
    remembered_sigma_m: FloatArray | None = None,
) -> tuple[float, FloatArray | None]:
    """The allowed lead, and the remembered return that limits it (None when a newest return,
    the maximum lead or the setpoint's own distance does)."""
    dx, dy = setpoint.x_m - pose.x_m, setpoint.y_m - pose.y_m
    lead = min(params.max_lead_m, math.hypot(dx, dy))
    speed = math.hypot(*velocity_xy)
    reach = body_radius_m + params.contact_margin_m + params.speed_margin_s * speed
    directions = [(dx, dy)]
    if not params.predict_way and speed > params.moving_mps:
        directions.append(velocity_xy)  # the motion's straight line instead of its predicted way
    remembered = np.zeros((0, 2)) if remembered_xy is None else remembered_xy
    spread = np.zeros(remembered.shape[0]) if remembered_sigma_m is None else remembered_sigma_m
    limit: FloatArray | None = None
    sets: list[_ReturnSet] = []
    for points, radius, kept in (
        (returns_xy, np.full(returns_xy.shape[0], reach), False),
        (remembered, reach + params.memory_margin_m + params.memory_sigmas * spread, True),
    ):
        if points.shape[0] == 0:
            continue
        rel = points - [pose.x_m, pose.y_m]
        nearest = float(np.min(np.hypot(rel[:, 0], rel[:, 1])))
        contact = np.minimum(radius, 0.95 * nearest)
        sets.append(_ReturnSet(rel, contact, kept, nearest < body_radius_m + params.contact_margin_m))
        for direction in directions:
            travel, i = first_contact(rel, direction, contact)
            allowed = max(0.0, travel - params.stop_margin_m)
            if allowed < lead:
                lead, limit = allowed, (points[i] if kept else None)
    if not (params.predict_way and speed > params.moving_mps and sets):
        return lead, limit
    # The way momentum takes to the setpoint must keep the berth too: the largest of the lead and
    # its halves whose predicted way does; else none, the vehicle brakes. Already inside the
    # plain berth (a tight door) even braking may carry it deeper, so there a way that comes no
    # deeper than braking's is allowed: moving along or away.
    norm = math.hypot(dx, dy)
    ux, uy = (dx / norm, dy / norm) if norm > 1e-9 else (0.0, 0.0)
    braking: list[tuple[float, FloatArray | None]] | None = None
    candidate = lead
    while True:
        touches = _touches(stop_path(velocity_xy, (ux * candidate, uy * candidate), params), sets)
        if candidate > 0.0 and any(depth > 0.0 for depth, _ in touches):
            if braking is None:
                braking = _touches(stop_path(velocity_xy, (0.0, 0.0), params), sets)
            if any(
                depth > 0.0 and not (returns.tight and depth <= brake + _DEPTH_TOLERANCE_M)
                for (depth, _), (brake, _), returns in zip(touches, braking, sets, strict=True)
            ):
                candidate = 0.0 if candidate < 0.1 else 0.5 * candidate
                continue
        if candidate == 0.0:  # braking, it may still come into the berth: the deepest return holds it
            depth, touched, kept = max(
                ((d, t, r.remembered) for (d, t), r in zip(touches, sets, strict=True)), key=lambda dtk: dtk[0]
            )
            if depth > 0.0 and touched is not None:
                return 0.0, (touched + np.array([pose.x_m, pose.y_m]) if kept else None)
        return candidate, limit if candidate == lead else None


_DEPTH_TOLERANCE_M = 0.005  # a way this little deeper into the berth than braking's is no deeper
_ALIGNED = math.sin(math.radians(1.0))  # velocity this close to the setpoint's bearing: on its line


def stop_path(velocity_xy: tuple[float, float], target_xy: tuple[float, float], params: LeadParams) -> FloatArray:
    """Where the vehicle goes (relative to where it is, in ``params.model_step_s`` steps) if the
    setpoint stayed at ``target_xy``: it coasts ``model_delay_s``, then flies to it as fast as it
    can still stop there, changing its velocity at ``model_accel_mps2`` at most."""
    dt, accel = params.model_step_s, params.model_accel_mps2
    vx, vy = velocity_xy
    tx, ty = target_xy
    x = y = 0.0
    out = [(0.0, 0.0)]
    steps = int(round(params.model_horizon_s / dt))
    coast = int(round(params.model_delay_s / dt))
    for k in range(steps):
        if k >= coast:
            ex, ey = tx - x, ty - y
            dist = math.hypot(ex, ey)
            speed = math.sqrt(2.0 * accel * dist)
            wx, wy = (ex / dist * speed, ey / dist * speed) if dist > 1e-9 else (0.0, 0.0)
            ax, ay = wx - vx, wy - vy
            dv = math.hypot(ax, ay)
            if dv > accel * dt:
                ax, ay = ax * accel * dt / dv, ay * accel * dt / dv
            vx, vy = vx + ax, vy + ay
            if dist < 0.01 and math.hypot(vx, vy) < 0.02:
                break
            # Heading straight for it, slow enough to stop on it: the rest is the setpoint's own
            # line, checked already.
            now = math.hypot(vx, vy)
            if now <= speed and vx * ex + vy * ey > 0.0 and abs(vx * ey - vy * ex) <= _ALIGNED * now * dist:
                out.append((tx, ty))
                break
        x, y = x + vx * dt, y + vy * dt
        out.append((x, y))
    return np.array(out)


def _touches(path: FloatArray, sets: list[_ReturnSet]) -> list[tuple[float, FloatArray | None]]:
    """For each set, how far the way ``path`` comes inside its contact distance of a return (0
    when it keeps clear) and that return (relative; None when clear)."""
    lo, hi = path.min(axis=0), path.max(axis=0)
    out: list[tuple[float, FloatArray | None]] = []
    for rel, contact, _, _ in sets:
        reach = contact[:, None]
        near = np.all((rel > lo - reach) & (rel < hi + reach), axis=1)
        if not near.any():
            out.append((0.0, None))
            continue
        pts = rel[near]
        dx, dy = path[:, 0:1] - pts[None, :, 0], path[:, 1:2] - pts[None, :, 1]
        closest = np.sqrt((dx * dx + dy * dy).min(axis=0))
        inside = contact[near] - closest
        i = int(np.argmax(inside))
        depth = float(inside[i])
        out.append((depth, pts[i]) if depth > 0.0 else (0.0, None))
    return out
