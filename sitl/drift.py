"""Odometry drift: the reported estimate is the true motion with Gaussian noise on each increment.

Noise grows with the square root of distance travelled, scaled so one keyframe-sized step of 1 m
gets the thesis's sigma (0.1 m per axis, 0.015 rad); ``scale`` multiplies both (0 = perfect).

The estimator reports its velocity too, as an autopilot's EKF does (ODOMETRY, LOCAL_POSITION_NED):
the true velocity turned into the estimate's frame, with white noise of ``velocity_sigma_mps`` per
axis (times ``scale``). It is not the drifting pose's derivative: that random walk, drawn on every
physics increment, makes the heading of motion over 0.2 s swing by tens of degrees, where an EKF
fusing an IMU holds its velocity to a few centimetres per second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.geometry import Pose2


@dataclass(frozen=True, slots=True)
class DriftParams:
    sigma_xy_m: float = 0.1  # per axis, per metre-sized step
    sigma_yaw_rad: float = 0.015  # per metre-sized step
    step_m: float = 1.0
    scale: float = 1.0
    velocity_sigma_mps: float = 0.05  # per axis, white, on the reported velocity


class OdometryDrift:
    """Integrates true body-frame increments into a drifting estimate."""

    def __init__(self, params: DriftParams, start: Pose2, rng: np.random.Generator) -> None:
        self.params = params
        self.estimate = start
        self.rng = rng

    def integrate(self, increment: Pose2) -> Pose2:
        """Apply one true body-frame increment with noise; return the new estimate."""
        p = self.params
        dist = math.hypot(increment.x_m, increment.y_m)
        if p.scale > 0.0 and dist > 0.0:
            k = p.scale * math.sqrt(dist / p.step_m)
            nx, ny = self.rng.normal(0.0, p.sigma_xy_m * k, 2)
            nyaw = self.rng.normal(0.0, p.sigma_yaw_rad * k)
            increment = Pose2(increment.x_m + nx, increment.y_m + ny, increment.yaw_rad + nyaw)
        self.estimate = self.estimate.compose(increment)
        return self.estimate
