"""A multirotor as a point mass with yaw, tracking a position + yaw setpoint given in the frame
of its own (drifting) state estimate, with speed, acceleration and yaw-rate limits."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.geometry import Pose2, wrap_angle
from sitl.drift import OdometryDrift


@dataclass(frozen=True, slots=True)
class VehicleParams:
    max_speed_mps: float = 1.5
    max_accel_mps2: float = 1.0
    max_yaw_rate_dps: float = 90.0
    body_radius_m: float = 0.25
    yaw_gain_per_s: float = 3.0


class Vehicle:
    """True state (pose, velocity) and the estimate the autopilot flies by."""

    def __init__(self, params: VehicleParams, start: Pose2, drift: OdometryDrift) -> None:
        self.params = params
        self.true_pose = start
        self.velocity = np.zeros(2)  # world frame, m/s
        self.yaw_rate_rps = 0.0
        self.drift = drift

    @property
    def estimate(self) -> Pose2:
        return self.drift.estimate

    def step(self, dt_s: float, target: Pose2 | None) -> None:
        """Advance ``dt_s`` towards ``target`` (estimate frame); None means brake and hold."""
        p = self.params
        est = self.drift.estimate
        if target is None:
            desired = np.zeros(2)
            yaw_err = 0.0
        else:
            ex, ey = target.x_m - est.x_m, target.y_m - est.y_m
            # The error as the autopilot sees it, flown in the true world.
            c, s = (
                math.cos(self.true_pose.yaw_rad - est.yaw_rad),
                math.sin(self.true_pose.yaw_rad - est.yaw_rad),
            )
            err = np.array([c * ex - s * ey, s * ex + c * ey])
            dist = float(np.hypot(*err))
            speed = min(p.max_speed_mps, math.sqrt(2.0 * p.max_accel_mps2 * dist) * 0.9, 2.0 * dist)
            desired = err / dist * speed if dist > 1e-6 else np.zeros(2)
            yaw_err = wrap_angle(target.yaw_rad - est.yaw_rad)
        dv = desired - self.velocity
        dv_norm = float(np.hypot(*dv))
        max_dv = p.max_accel_mps2 * dt_s
        if dv_norm > max_dv:
            dv *= max_dv / dv_norm
        self.velocity = self.velocity + dv
        max_rate = math.radians(p.max_yaw_rate_dps)
        self.yaw_rate_rps = max(-max_rate, min(max_rate, p.yaw_gain_per_s * yaw_err))
        move = self.velocity * dt_s
        dyaw = self.yaw_rate_rps * dt_s
        old = self.true_pose
        self.true_pose = Pose2(old.x_m + move[0], old.y_m + move[1], wrap_angle(old.yaw_rad + dyaw))
        self.drift.integrate(old.between(self.true_pose))
