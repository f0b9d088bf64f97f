"""The in-process simulator: world, sensor, vehicle with drifting odometry, SLAM back end, and a
simulation clock. Deterministic for a seed; nothing sleeps on wall time."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.core.geometry import Pose2
from companion.core.messages import DepthScan, LoopClosure, Odometry
from sitl.depth_sensor import DepthSensor, SensorParams
from sitl.drift import DriftParams, OdometryDrift
from sitl.slam import SimulatedSlam, SlamParams
from sitl.vehicle import Vehicle, VehicleParams
from sitl.world import World


@dataclass(frozen=True, slots=True)
class SimParams:
    sensor: SensorParams = field(default_factory=SensorParams)
    vehicle: VehicleParams = field(default_factory=VehicleParams)
    drift: DriftParams = field(default_factory=DriftParams)
    slam: SlamParams = field(default_factory=SlamParams)
    physics_rate_hz: float = 50.0


@dataclass(frozen=True, slots=True)
class SensorFrame:
    """What the vehicle reports at one sensor tick, plus the truth for evaluation."""

    stamp_s: float
    odometry: Odometry
    scan: DepthScan
    loop_closure: LoopClosure | None
    true_pose: Pose2


class Simulation:
    """Steps the physics at ``physics_rate_hz`` and produces a frame per sensor tick."""

    def __init__(self, world: World, params: SimParams | None = None, seed: int = 0) -> None:
        self.world = world
        self.params = params or SimParams()
        rng = np.random.default_rng(seed)
        p = self.params
        # The estimate starts at the true start pose (the odometry frame is the map frame at t=0).
        self.vehicle = Vehicle(p.vehicle, world.start, OdometryDrift(p.drift, world.start, rng))
        self.sensor = DepthSensor(world.walls, p.sensor, rng)
        self.slam = SimulatedSlam(p.slam, world.walls)
        # The reported velocity's noise has a stream of its own: the drift is drawn as before.
        self._velocity_rng = np.random.default_rng([seed, 7])
        self.time_s = 0.0
        self.collisions = 0
        self.path_length_m = 0.0
        self._dt = 1.0 / p.physics_rate_hz
        self._ticks_per_scan = max(1, round(p.physics_rate_hz / p.sensor.rate_hz))

    @property
    def crashed(self) -> bool:
        return self.collisions > 0

    def frame(self) -> SensorFrame:
        """Sense at the current time (no motion)."""
        v = self.vehicle
        scan = self.sensor.scan(v.true_pose, self.time_s)
        closure = self.slam.observe(self.time_s, v.true_pose)
        odometry = Odometry(self.time_s, v.estimate, 0, self._reported_velocity())
        return SensorFrame(self.time_s, odometry, scan, closure, v.true_pose)

    def _reported_velocity(self) -> tuple[float, float]:
        """The estimator's velocity: the true one in the estimate's frame, with its noise."""
        v = self.vehicle
        turn = v.estimate.yaw_rad - v.true_pose.yaw_rad
        c, s = math.cos(turn), math.sin(turn)
        vx, vy = float(v.velocity[0]), float(v.velocity[1])
        d = self.params.drift
        sigma = d.velocity_sigma_mps * d.scale
        nx, ny = self._velocity_rng.normal(0.0, sigma, 2) if sigma > 0.0 else (0.0, 0.0)
        return (c * vx - s * vy + float(nx), s * vx + c * vy + float(ny))

    def advance(self, target: Pose2 | None) -> SensorFrame:
        """Fly towards ``target`` (estimate frame) until the next sensor tick, then sense."""
        radius = self.params.vehicle.body_radius_m
        for _ in range(self._ticks_per_scan):
            before = self.vehicle.true_pose
            self.vehicle.step(self._dt, target)
            self.time_s = round(self.time_s + self._dt, 9)
            after = self.vehicle.true_pose
            self.path_length_m += math.hypot(after.x_m - before.x_m, after.y_m - before.y_m)
            if self.world.clearance_at(after.x_m, after.y_m) < radius:
                self.collisions += 1
                break
        return self.frame()
