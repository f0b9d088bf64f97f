"""A simulated SLAM back end (thesis 3.1): it recognises places the vehicle has been before.

Every metre travelled it remembers a *place* (stamp, true pose). When the vehicle comes back
within range of an old place with a clear line of sight, it reports a loop closure between the
two moments with the true relative transform, as a real back end would report its measurement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.core.geometry import FloatArray, Pose2
from companion.core.messages import LoopClosure
from sitl.depth_sensor import cast_rays


@dataclass(frozen=True, slots=True)
class SlamParams:
    enabled: bool = True
    place_spacing_m: float = 1.0
    range_m: float = 4.0
    min_travel_between_m: float = 5.0  # path length since the place: not just the last few steps
    min_interval_s: float = 1.0
    max_yaw_difference_rad: float = math.pi  # like the thesis: any heading, given line of sight


class SimulatedSlam:
    def __init__(self, params: SlamParams, walls: FloatArray) -> None:
        self.params = params
        self.walls = walls
        self._stamps: list[float] = []
        self._poses: list[Pose2] = []
        self._travel_at: list[float] = []
        self._travel_m = 0.0
        self._last: Pose2 | None = None
        self._last_closure_s = -math.inf

    def observe(self, stamp_s: float, true_pose: Pose2) -> LoopClosure | None:
        """Feed the true pose at a sensor tick; return a loop closure when one is recognised."""
        p = self.params
        if self._last is not None:
            self._travel_m += self._last.distance_to(true_pose)
        self._last = true_pose
        closure = self._recognise(stamp_s, true_pose) if p.enabled else None
        if not self._poses or self._poses[-1].distance_to(true_pose) >= p.place_spacing_m:
            self._stamps.append(stamp_s)
            self._poses.append(true_pose)
            self._travel_at.append(self._travel_m)
        return closure

    def _recognise(self, stamp_s: float, pose: Pose2) -> LoopClosure | None:
        p = self.params
        if stamp_s - self._last_closure_s < p.min_interval_s or not self._poses:
            return None
        xy = np.array([[q.x_m, q.y_m] for q in self._poses])
        travel = np.array(self._travel_at)
        yaw = np.array([q.yaw_rad for q in self._poses])
        d = np.hypot(xy[:, 0] - pose.x_m, xy[:, 1] - pose.y_m)
        dyaw = np.abs((yaw - pose.yaw_rad + np.pi) % (2 * np.pi) - np.pi)
        ok = (d <= p.range_m) & (self._travel_m - travel >= p.min_travel_between_m) & (dyaw <= p.max_yaw_difference_rad)
        for i in np.flatnonzero(ok)[np.argsort(d[ok])]:
            if self._line_of_sight(pose, self._poses[i], float(d[i])):
                self._last_closure_s = stamp_s
                return LoopClosure(self._stamps[i], stamp_s, self._poses[i].between(pose))
        return None

    def _line_of_sight(self, a: Pose2, b: Pose2, dist_m: float) -> bool:
        if dist_m < 1e-6:
            return True
        angle = np.array([math.atan2(b.y_m - a.y_m, b.x_m - a.x_m)])
        hit = cast_rays(np.array([a.x_m, a.y_m]), angle, self.walls, dist_m)
        return not bool(np.isfinite(hit[0]))
