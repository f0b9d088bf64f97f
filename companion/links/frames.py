"""Frame conversions at the edge: MAVLink's NED / FRD to the core's frame, and back.

The core works in a right-handed planar frame with yaw counter-clockwise (x east, y north when the
autopilot's local frame is north-aligned). MAVLink's local frame is NED (x north, y east, z down,
yaw clockwise from north) and its body frame FRD (x forward, y right). The map between the two is
its own inverse: swap x and y, and yaw -> pi/2 - yaw.
"""

from __future__ import annotations

import math

import numpy as np

from companion.core.geometry import FloatArray, Pose2, wrap_angle


def ned_to_core(north_m: float, east_m: float, yaw_ned_rad: float) -> Pose2:
    """A NED position and heading (clockwise from north) as a core pose."""
    return Pose2(east_m, north_m, wrap_angle(math.pi / 2.0 - yaw_ned_rad))


def core_to_ned(x_m: float, y_m: float, yaw_rad: float) -> tuple[float, float, float]:
    """A core position and yaw as NED (north, east, heading clockwise from north in (-pi, pi])."""
    return y_m, x_m, wrap_angle(math.pi / 2.0 - yaw_rad)


def frd_bearings_to_core(angles_frd_rad: FloatArray) -> FloatArray:
    """Body FRD angles (clockwise from forward) as core bearings (counter-clockwise)."""
    return -np.asarray(angles_frd_rad, dtype=np.float64)


def yaw_from_quaternion(w: float, x: float, y: float, z: float) -> float:
    """Heading (rotation about the down axis) of a NED attitude quaternion, in radians."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw_rad: float) -> tuple[float, float, float, float]:
    """A level attitude with this heading, as (w, x, y, z)."""
    return math.cos(yaw_rad / 2.0), 0.0, 0.0, math.sin(yaw_rad / 2.0)
