"""OBSTACLE_DISTANCE (MAVLink message 330) to and from the core's :class:`DepthScan`.

Semantics from the MAVLink spec: ``distances[72]`` in centimetres, bin ``i`` at
``angle_offset + i * increment_f`` degrees clockwise from the frame's forward (``MAV_FRAME_BODY_FRD``)
or from north (``MAV_FRAME_GLOBAL`` / ``MAV_FRAME_LOCAL_NED``, the spec's default); ``UINT16_MAX``
marks an unused bin, ``max_distance + 1`` no obstacle within range, and 0 an obstacle touching the
sensor. Pure functions over plain values, so both ends (the sitl sender and the companion's link)
share one tested definition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.errors import ScanError
from companion.core.messages import DepthScan
from companion.links.frames import frd_bearings_to_core

UINT16_MAX = 65535
BINS = 72
MAV_FRAME_GLOBAL = 0
MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
NORTH_ALIGNED_FRAMES = (MAV_FRAME_GLOBAL, MAV_FRAME_LOCAL_NED)


@dataclass(frozen=True, slots=True)
class ObstacleDistance:
    """The fields of one OBSTACLE_DISTANCE message that carry the scan."""

    time_usec: int
    distances_cm: tuple[int, ...]
    increment_deg: float
    angle_offset_deg: float
    min_distance_cm: int
    max_distance_cm: int
    frame: int = MAV_FRAME_BODY_FRD


def encode_scan(scan: DepthScan, time_usec: int) -> ObstacleDistance:
    """A body-frame scan with evenly spaced bearings as one message (at most 72 bins: wider scans
    are reduced by keeping the nearest return of each group of neighbouring rays)."""
    bearings = scan.bearings_rad[::-1]  # FRD order: first bin leftmost, clockwise after
    ranges = scan.ranges_m[::-1]
    group = max(1, math.ceil(bearings.size / BINS))
    n = bearings.size // group
    step = np.diff(scan.bearings_rad)
    if step.size and np.ptp(step) > 1e-6 * max(1.0, float(step.mean())):
        raise ScanError("OBSTACLE_DISTANCE needs evenly spaced bearings")
    min_cm = max(0, round(scan.min_range_m * 100.0))
    max_cm = min(UINT16_MAX - 2, round(scan.max_range_m * 100.0))
    r = ranges[: n * group].reshape(n, group)
    with np.errstate(invalid="ignore"):
        r = np.where(np.isnan(r), np.inf, r)  # an invalid reading says nothing: no return
        nearest = r.min(axis=1)
    cm = np.where(
        nearest >= scan.max_range_m,
        max_cm + 1,
        np.where(nearest < scan.min_range_m, 0, np.round(np.clip(nearest, 0.0, None) * 100.0)),
    ).astype(np.int64)
    distances = np.full(BINS, UINT16_MAX, dtype=np.int64)
    distances[:n] = np.clip(cm, 0, max_cm + 1)
    first_deg = -math.degrees(float(bearings[group // 2 : n * group : group][0]))
    increment_deg = math.degrees(float(np.mean(step))) * group if step.size else 0.0
    return ObstacleDistance(
        time_usec, tuple(int(d) for d in distances), increment_deg, first_deg, min_cm, max_cm, MAV_FRAME_BODY_FRD
    )


def decode_scan(msg: ObstacleDistance, stamp_s: float, vehicle_yaw_ned_rad: float | None = None) -> DepthScan:
    """One message as a body-frame scan; raises :class:`ScanError` on a message that cannot be one.

    North-aligned frames need the vehicle's heading at the message's time to turn into body frame.
    """
    if len(msg.distances_cm) != BINS:
        raise ScanError(f"OBSTACLE_DISTANCE needs {BINS} distances, got {len(msg.distances_cm)}")
    if not (math.isfinite(msg.increment_deg) and 0.0 < msg.increment_deg < 360.0):
        raise ScanError(f"OBSTACLE_DISTANCE increment must be in (0, 360) degrees, got {msg.increment_deg}")
    if not math.isfinite(msg.angle_offset_deg):
        raise ScanError("OBSTACLE_DISTANCE angle_offset must be finite")
    if not 0 <= msg.min_distance_cm < msg.max_distance_cm:
        raise ScanError(
            f"OBSTACLE_DISTANCE needs min_distance < max_distance, got {msg.min_distance_cm}/{msg.max_distance_cm}"
        )
    d = np.asarray(msg.distances_cm, dtype=np.int64)
    used = np.flatnonzero(d != UINT16_MAX)
    if used.size < 2:
        raise ScanError("OBSTACLE_DISTANCE has fewer than two used bins")
    offset_deg = msg.angle_offset_deg
    if msg.frame in NORTH_ALIGNED_FRAMES:
        if vehicle_yaw_ned_rad is None:
            raise ScanError("a north-aligned OBSTACLE_DISTANCE needs the vehicle heading")
        offset_deg -= math.degrees(vehicle_yaw_ned_rad)
    elif msg.frame != MAV_FRAME_BODY_FRD:
        raise ScanError(f"OBSTACLE_DISTANCE frame {msg.frame} is not supported (use MAV_FRAME_BODY_FRD)")
    bearings = frd_bearings_to_core(np.radians(offset_deg + used * msg.increment_deg))
    cm = d[used]
    max_m = msg.max_distance_cm / 100.0
    ranges = np.where(cm > msg.max_distance_cm, np.inf, cm / 100.0)
    ranges = np.where(cm < msg.min_distance_cm, -np.inf, ranges)
    # Bearings in (-pi, pi] around forward, ascending counter-clockwise.
    bearings = (bearings + math.pi) % (2.0 * math.pi) - math.pi
    order = np.argsort(bearings, kind="stable")
    return DepthScan(stamp_s, bearings[order], ranges[order], max_m, msg.min_distance_cm / 100.0)
