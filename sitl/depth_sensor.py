"""A 2D depth sensor: rays cast against the walls, vectorised over rays and walls."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.geometry import FloatArray, Pose2
from companion.core.messages import DepthScan


@dataclass(frozen=True, slots=True)
class SensorParams:
    fov_deg: float = 90.0
    rays: int = 64
    max_range_m: float = 5.0
    min_range_m: float = 0.1
    rate_hz: float = 10.0
    range_noise_m: float = 0.02

    def bearings_rad(self) -> FloatArray:
        half = math.radians(self.fov_deg) / 2.0
        return np.linspace(-half, half, self.rays)


def cast_rays(origin_xy: FloatArray, angles_rad: FloatArray, walls: FloatArray, max_range_m: float) -> FloatArray:
    """Distance along each ray (world angles) to the first wall, ``inf`` when none within range."""
    if walls.shape[0] == 0:
        return np.full(np.shape(angles_rad), np.inf)
    d = np.column_stack((np.cos(angles_rad), np.sin(angles_rad)))  # (R, 2)
    a = walls[:, 0, :]  # (M, 2)
    e = walls[:, 1, :] - a  # (M, 2)
    w = a - origin_xy  # (M, 2)
    # Solve origin + t d = a + u e  ->  t = cross(w, e) / cross(d, e), u = cross(w, d) / cross(d, e)
    denom = d[:, 0:1] * e[None, :, 1] - d[:, 1:2] * e[None, :, 0]  # (R, M)
    cross_we = w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]  # (M,)
    cross_wd = w[None, :, 0] * d[:, 1:2] - w[None, :, 1] * d[:, 0:1]  # (R, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = cross_we[None, :] / denom
        u = cross_wd / denom
    hit = (np.abs(denom) > 1e-12) & (t >= 0.0) & (u >= 0.0) & (u <= 1.0)
    t = np.where(hit, t, np.inf)
    dist = t.min(axis=1)
    return np.where(dist <= max_range_m, dist, np.inf)


class DepthSensor:
    """Scans from the true pose; no return reads as exactly ``max_range_m``."""

    def __init__(self, walls: FloatArray, params: SensorParams, rng: np.random.Generator) -> None:
        self.walls = walls
        self.params = params
        self.rng = rng
        self.bearings = params.bearings_rad()

    def true_ranges(self, pose: Pose2) -> FloatArray:
        return cast_rays(
            np.array([pose.x_m, pose.y_m]),
            self.bearings + pose.yaw_rad,
            self.walls,
            self.params.max_range_m,
        )

    def scan(self, pose: Pose2, stamp_s: float) -> DepthScan:
        p = self.params
        r = self.true_ranges(pose)
        noisy = r + self.rng.normal(0.0, p.range_noise_m, r.shape) if p.range_noise_m > 0 else r
        ranges = np.where(
            np.isfinite(r) & (noisy < p.max_range_m),
            np.maximum(noisy, p.min_range_m),
            p.max_range_m,
        )
        return DepthScan(stamp_s, self.bearings.copy(), ranges, p.max_range_m, p.min_range_m)
