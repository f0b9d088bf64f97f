"""The values that cross the core's boundary: odometry, scans, loop closures and setpoints.

Frames: every pose is in the odometry frame of the vehicle's own state estimate (x forward at
start, y left, yaw CCW), which drifts. Links convert NED/FRD to this frame once, at the edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.errors import ScanError
from companion.core.geometry import FloatArray, Pose2


@dataclass(frozen=True, slots=True)
class Odometry:
    """A state estimate sample: pose in the odometry frame at ``stamp_s`` (vehicle time).

    ``velocity_xy`` is the estimator's own velocity (m/s, odometry frame), when the link carries
    one: an autopilot's EKF fuses the IMU, so it is steadier than the pose differenced over a
    fraction of a second, whose drift makes the heading of motion swing. None: the explorer
    differences the pose."""

    stamp_s: float
    pose: Pose2
    reset_counter: int = 0
    velocity_xy: tuple[float, float] | None = None


@dataclass(frozen=True, slots=True)
class DepthScan:
    """A planar depth scan in the body frame: one range per bearing.

    ``bearings_rad`` increase strictly (counter-clockwise). Range conventions follow REP 117:
    ``+inf`` or ``>= max_range_m`` is no return within range, ``-inf`` an object closer than
    ``min_range_m``, NaN (or a negative or sub-minimum value) an invalid reading.
    """

    stamp_s: float
    bearings_rad: FloatArray
    ranges_m: FloatArray
    max_range_m: float
    min_range_m: float = 0.1

    def __post_init__(self) -> None:
        b = np.asarray(self.bearings_rad, dtype=np.float64)
        r = np.asarray(self.ranges_m, dtype=np.float64)
        object.__setattr__(self, "bearings_rad", b)
        object.__setattr__(self, "ranges_m", r)
        if b.ndim != 1 or r.shape != b.shape or b.size < 2:
            raise ScanError(f"scan needs >= 2 bearings and one range each, got {b.shape}/{r.shape}")
        if not np.all(np.isfinite(b)):
            raise ScanError("scan bearings must be finite")
        if np.any(np.diff(b) <= 0.0):
            raise ScanError("scan bearings must increase strictly")
        if b[-1] - b[0] >= 2.0 * math.pi:
            raise ScanError("scan bearings must span less than a full turn")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0.0):
            raise ScanError(f"max_range_m must be finite and positive, got {self.max_range_m}")
        if not (math.isfinite(self.min_range_m) and 0.0 <= self.min_range_m < self.max_range_m):
            raise ScanError(f"min_range_m must lie in [0, max_range_m), got {self.min_range_m}")
        if not math.isfinite(self.stamp_s):
            raise ScanError("scan stamp must be finite")

    def capped(self, max_range_m: float) -> DepthScan:
        """The scan as a sensor of at most ``max_range_m`` would report it: returns from farther
        are no return (a range-limit frontier there), and that is its maximum range. Itself when
        its range is no longer. Polygons grow with the range (their arcs keep a vertex spacing):
        a sensor claiming 10 km of range made one step take 20 s."""
        if self.max_range_m <= max_range_m:
            return self
        if self.min_range_m >= max_range_m:
            raise ScanError(
                f"the scan's minimum range {self.min_range_m:g} m is at or beyond the {max_range_m:g} m the map takes"
            )
        r = self.ranges_m
        return DepthScan(
            self.stamp_s, self.bearings_rad, np.where(r >= max_range_m, np.inf, r), max_range_m, self.min_range_m
        )


@dataclass(frozen=True, slots=True)
class LoopClosure:
    """A SLAM back end's loop closure: the vehicle at ``current_stamp_s`` saw the place it was at
    ``earlier_stamp_s``; ``earlier_to_current`` is the measured transform between the two poses."""

    earlier_stamp_s: float
    current_stamp_s: float
    earlier_to_current: Pose2


@dataclass(frozen=True, slots=True)
class Setpoint:
    """A position + yaw target in the odometry frame."""

    x_m: float
    y_m: float
    yaw_rad: float

    def is_finite(self) -> bool:
        return math.isfinite(self.x_m) and math.isfinite(self.y_m) and math.isfinite(self.yaw_rad)
