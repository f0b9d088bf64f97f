"""How far ahead of the vehicle a position setpoint may lie: the companion's speed limit.

An autopilot flies a far position target as fast as its own limits allow (PX4 offboard up to
MPC_XY_VEL_MAX, 12 m/s by default) and a near one about as fast as its position gain makes of the
distance, braking to stop on it. So the setpoint is kept within a maximum lead of the vehicle, and
within the free travel the newest scan shows ahead (towards the setpoint, and along the vehicle's
motion, which carries it on while it turns): the vehicle comes in slowly enough to stop short of a
seen obstacle, whatever the planner asks next.

Returns remembered from earlier scans (out of view now) hold the vehicle too, with more berth. When
they alone hold it where the newest scan would let it go, the vehicle turns to look at the one in its
way (:func:`limit_lead_facing_memory`): the sensor then sees it again, or sees through it, and the scan
decides. Forgetting it instead (an age limit) let a vehicle that had hovered beside a thin wall's
end turn onto it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
    stop_margin_m: float = 0.1  # the setpoint stays this much short of touching
    moving_mps: float = 0.1  # above this speed the motion's own direction is checked too
    # The contact radius grows by this many seconds of speed: at speed the vehicle does not hold
    # a line to the centimetre (a turn, drift, the autopilot's own tracking), and a corner its
    # line passes 0.3 m from at 1.5 m/s is one it may hit; it cannot brake in time once it sees it.
    speed_margin_s: float = 0.15
    # Remembered returns hold the vehicle when they leave it at most this much lead while the
    # newest scan alone would leave it at least ``look_lead_m``: then it looks at what holds it.
    hold_m: float = 0.05
    look_lead_m: float = 0.2


def limit_lead(
    setpoint: Setpoint,
    pose: Pose2,
    velocity_xy: tuple[float, float],
    returns_xy: FloatArray,
    body_radius_m: float,
    params: LeadParams,
    remembered_xy: FloatArray | None = None,
) -> Setpoint:
    """The setpoint moved along its line from the vehicle to at most the allowed lead (yaw kept).

    ``velocity_xy``, ``returns_xy`` (the newest scan's obstacle points) and ``remembered_xy``
    (earlier scans') are in the setpoint's frame. Already closer to a return than the body
    radius and contact margin (a tight door) the vehicle may move along or away, only not closer
    still. Only returns count, never the map: a drifted view's wall placed on the vehicle must
    not shrink the berth to nothing (office 2 flew into a wall that way). The faster it moves,
    the wider a berth its line must give a return.
    """
    lead, _ = _lead_m(setpoint, pose, velocity_xy, returns_xy, body_radius_m, params, remembered_xy)
    return _within(setpoint, pose, lead)


def limit_lead_facing_memory(
    setpoint: Setpoint,
    pose: Pose2,
    velocity_xy: tuple[float, float],
    returns_xy: FloatArray,
    body_radius_m: float,
    params: LeadParams,
    remembered_xy: FloatArray,
) -> tuple[Setpoint, FloatArray | None]:
    """:func:`limit_lead`; but when remembered returns alone hold the vehicle (see
    :class:`LeadParams`), the setpoint faces the one its way touches first, so the sensor sees it
    again. Returns the setpoint and that return (None when nothing remembered holds it)."""
    held, blocker = _lead_m(setpoint, pose, velocity_xy, returns_xy, body_radius_m, params, remembered_xy)
    limited = _within(setpoint, pose, held)
    if blocker is None or held > params.hold_m:
        return limited, None
    free, _ = _lead_m(setpoint, pose, velocity_xy, returns_xy, body_radius_m, params, None)
    if free < params.look_lead_m:
        return limited, None
    yaw = math.atan2(float(blocker[1]) - pose.y_m, float(blocker[0]) - pose.x_m)
    return Setpoint(limited.x_m, limited.y_m, yaw), blocker


def _within(setpoint: Setpoint, pose: Pose2, lead_m: float) -> Setpoint:
    """The setpoint moved along its line from the vehicle to at most ``lead_m`` away (yaw kept)."""
    dx, dy = setpoint.x_m - pose.x_m, setpoint.y_m - pose.y_m
    dist = math.hypot(dx, dy)
    if lead_m >= dist:
        return setpoint
    k = lead_m / dist
    return Setpoint(pose.x_m + k * dx, pose.y_m + k * dy, setpoint.yaw_rad)


def _lead_m(
    setpoint: Setpoint,
    pose: Pose2,
    velocity_xy: tuple[float, float],
    returns_xy: FloatArray,
    body_radius_m: float,
    params: LeadParams,
    remembered_xy: FloatArray | None,
) -> tuple[float, FloatArray | None]:
    """The allowed lead, and the remembered return that limits it (None when a newest return,
    the maximum lead or the setpoint's own distance does)."""
    dx, dy = setpoint.x_m - pose.x_m, setpoint.y_m - pose.y_m
    lead = min(params.max_lead_m, math.hypot(dx, dy))
    speed = math.hypot(*velocity_xy)
    reach = body_radius_m + params.contact_margin_m + params.speed_margin_s * speed
    directions = [(dx, dy)]
    if speed > params.moving_mps:
        directions.append(velocity_xy)
    remembered = np.zeros((0, 2)) if remembered_xy is None else remembered_xy
    limit: FloatArray | None = None
    for points, radius, kept in ((returns_xy, reach, False), (remembered, reach + params.memory_margin_m, True)):
        if points.shape[0] == 0:
            continue
        rel = points - [pose.x_m, pose.y_m]
        contact = min(radius, 0.95 * float(np.min(np.hypot(rel[:, 0], rel[:, 1]))))
        for direction in directions:
            travel, i = first_contact(rel, direction, contact)
            allowed = max(0.0, travel - params.stop_margin_m)
            if allowed < lead:
                lead, limit = allowed, (points[i] if kept else None)
    return lead, limit
