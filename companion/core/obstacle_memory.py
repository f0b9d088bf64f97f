"""The obstacle returns the setpoint lead remembers from recent scans, kept in line with the newest.

A door jamb that has left the sensor's field of view beside the vehicle must still stop it short
of contact (:mod:`companion.core.setpoint_lead`), so the returns of the last scans are kept, in
the odometry frame. But odometry drifts: a return placed by the pose of a scan taken a metre of
travel ago lies off by that metre's drift relative to the vehicle now. With the thesis's drift
(0.1 m per axis per metre-sized step) the remembered returns near the vehicle lay up to 0.37 m
off the true walls (p99 0.22 m; the newest scan's 0.045 m), and one vehicle flew into a thin wall's
end it remembered 0.27 m off (session 47).

So each new scan first aligns the memory to itself (:meth:`RecentReturns.align`): the remembered
returns its view takes in are matched to its walls (point-to-line ICP against the prior of no
drift, each return paired with the wall on its ray), and the motion found moves every
remembered return, those out of view too. A scan-to-map odometry, for the lead's memory alone:
the map's views and the planner are not touched. It roughly halved how far off remembered
returns near the vehicle lie (p90 0.12 -> 0.06 m on a generated building, 0.10 -> 0.08 m on
office; session 48).

Where the walls fix nothing (along a corridor; through a door, seeing only the far room's wall)
the memory stays as odometry put it, and there it was still 0.1-0.3 m off: so what each alignment
leaves unknown adds to how far off each remembered scan may lie (:meth:`RecentReturns.sigmas_m`),
and the lead gives a return that much more berth (``LeadParams.memory_sigmas``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from companion.core.fov_polygon import has_return, in_view
from companion.core.geometry import FloatArray, Pose2
from companion.core.messages import DepthScan
from companion.core.scan_matching import solve_step


@dataclass(frozen=True, slots=True)
class MemoryAlignParams:
    """Tuning for :meth:`RecentReturns.align`."""

    enabled: bool = True
    # The prior on no drift since the last scan: the odometry's drift over the travel since (per
    # axis, and heading, growing with the square root of the distance, as a random walk's), with
    # a floor. Where the walls fix the motion they decide; where they fix nothing it stays, and a
    # hovering vehicle's memory stays put (else each match's own noise would random-walk it).
    drift_xy_m_per_sqrt_m: float = 0.1
    drift_yaw_rad_per_sqrt_m: float = 0.015
    min_sigma_xy_m: float = 0.002
    min_sigma_yaw_rad: float = 0.0005
    # Two neighbouring rays' returns this close lie on one wall, the segment between them.
    wall_max_gap_m: float = 0.3
    # A remembered return pairs with the wall its bearing from the sensor falls on (projective
    # association: one lookup, where the nearest of all walls costs a distance to each) when it
    # lies this near its line; the gate shrinks to the last value over the iterations.
    gates_m: tuple[float, ...] = (0.3, 0.15, 0.1, 0.1)
    # The returns' spread about their wall (range noise, on both scans): it weighs them against
    # the prior, and each weighs 1 / (1 + (r / spread)^2), so a few off any wall pull little.
    spread_m: float = 0.03
    # Taken when this many remembered returns lie within ``inlier_m`` of their walls after it.
    min_inliers: int = 10
    inlier_m: float = 0.06
    # How far from the vehicle a heading error is weighed at, in how far off the memory may lie
    # (:meth:`RecentReturns.sigmas_m`): what holds the vehicle back lies within about this.
    lever_m: float = 1.0


@dataclass(frozen=True, slots=True)
class ScanWalls:
    """A scan's surfaces, ray by ray, in its sensor's frame: ``starts_xy[j]`` to ``ends_xy[j]`` joins
    ray j's return to ray j+1's, where ``ok[j]`` (both returned, no farther apart than the gap);
    ``normals_xy[j]`` is its unit normal (each alignment asks it of every pairing again)."""

    bearings_rad: FloatArray
    starts_xy: FloatArray
    ends_xy: FloatArray
    ok: NDArray[np.bool_]
    normals_xy: FloatArray


def scan_walls(scan: DepthScan, no_return_margin_m: float, max_gap_m: float) -> ScanWalls:
    """The scan's surfaces (:class:`ScanWalls`): a segment between each two neighbouring rays'
    returns no farther apart than ``max_gap_m`` (farther, the nearer one occludes the other, or
    there is an opening between them)."""
    hit = has_return(scan, no_return_margin_m)
    r = np.where(hit, scan.ranges_m, 0.0)
    b = scan.bearings_rad
    pts = np.column_stack((r * np.cos(b), r * np.sin(b)))
    seg = pts[1:] - pts[:-1]
    gap = np.hypot(seg[:, 0], seg[:, 1])
    normals = np.column_stack((-seg[:, 1], seg[:, 0])) / np.maximum(gap, 1e-12)[:, None]
    return ScanWalls(b, pts[:-1], pts[1:], hit[:-1] & hit[1:] & (gap <= max_gap_m), normals)


class Alignment(NamedTuple):
    """A motion found by :func:`align_to_walls` and how well it is known: its covariance (x, y,
    heading; the heading's about the sensor)."""

    motion: Pose2
    covariance: FloatArray


def align_to_walls(
    points_xy: FloatArray, walls: ScanWalls, prior_sigma_xy_m: float, prior_sigma_yaw_rad: float, p: MemoryAlignParams
) -> Alignment | None:
    """The rigid motion (sensor frame) that moves ``points_xy`` (sensor frame) onto ``walls``,
    weighed against no motion as a prior (see :class:`MemoryAlignParams`), or None when fewer
    than ``p.min_inliers`` of them end on a wall."""
    pose = Pose2.identity()
    prior_var = np.array([prior_sigma_xy_m, prior_sigma_xy_m, prior_sigma_yaw_rad]) ** 2
    weights = p.spread_m**2 / prior_var
    for gate_m in p.gates_m:
        moved = pose.apply(points_xy)
        paired, on_xy, normals, off = _pair_with_walls(moved, walls)
        use = paired & (off < gate_m)
        if int(np.count_nonzero(use)) < p.min_inliers:
            return None
        step = solve_step(moved[use], on_xy[use], normals[use], (pose, Pose2.identity(), weights), p.spread_m)
        pose = step.compose(pose)
    moved = pose.apply(points_xy)
    paired, _, normals, off = _pair_with_walls(moved, walls)
    on = paired & (off < p.inlier_m)
    if int(np.count_nonzero(on)) < p.min_inliers:
        return None
    # Each return on a wall fixes the motion along its wall's normal (and the heading by its
    # lever about the sensor) to the returns' spread; the prior fixes the rest.
    n, q = normals[on], moved[on]
    jac = np.column_stack((n, n[:, 1] * q[:, 0] - n[:, 0] * q[:, 1]))
    w = 1.0 / (1.0 + (off[on] / p.spread_m) ** 2)
    information = jac.T @ (w[:, None] * jac) / p.spread_m**2 + np.diag(1.0 / prior_var)
    return Alignment(pose, np.asarray(np.linalg.inv(information), dtype=np.float64))


def _pair_with_walls(
    points_xy: FloatArray, walls: ScanWalls
) -> tuple[NDArray[np.bool_], FloatArray, FloatArray, FloatArray]:
    """Each point's wall: the one between the two rays its bearing falls between. Returns whether
    it has one, a point on it (its start), its unit normal and the point's distance to its line."""
    b = walls.bearings_rad
    j = np.searchsorted(b, np.arctan2(points_xy[:, 1], points_xy[:, 0])) - 1
    inside = (j >= 0) & (j < b.size - 1)
    j = np.where(inside, j, 0)
    start, normals = walls.starts_xy[j], walls.normals_xy[j]
    rel = points_xy - start
    off = np.abs(normals[:, 0] * rel[:, 0] + normals[:, 1] * rel[:, 1])
    return inside & walls.ok[j], start, normals, off


class RecentReturns:
    """Obstacle returns of the scans of the last ``memory_s`` seconds and ``memory_m`` metres of
    travel, in the odometry frame.

    Held as one array of points, oldest scan first, beside each scan's stamp, travel, point count
    and covariance: a step moves, grows and asks all of them, so each is one numpy call, not one
    per scan."""

    def __init__(
        self, memory_s: float, memory_m: float, margin_m: float = 0.0, align: MemoryAlignParams | None = None
    ) -> None:
        self.memory_s = memory_s
        self.memory_m = memory_m
        self.margin_m = margin_m  # see in_view: seen through this near the view's edge, kept
        # Not aligned unless told: perfect poses (the grid baseline's) leave nothing to align.
        self.align_params = align or MemoryAlignParams(enabled=False)
        self._points: FloatArray = np.zeros((0, 2))  # every scan's, oldest first (odometry frame)
        self._stamps_s: list[float] = []
        self._travelled_m: list[float] = []
        self._counts: list[int] = []  # each scan's number of points
        # Each scan's covariance (x, y) of where its points lie relative to the vehicle: the drift
        # since the scan that the alignments since could not take out.
        self._covariances: FloatArray = np.zeros((0, 2, 2))

    def add(self, stamp_s: float, travelled_m: float, points_xy: FloatArray) -> None:
        drop_last = 0
        while drop_last < len(self._stamps_s) and self._stamps_s[-1 - drop_last] > stamp_s:  # the clock went back
            drop_last += 1
        kept = len(self._stamps_s) - drop_last
        drop_first = 0
        while drop_first < kept and (
            self._stamps_s[drop_first] < stamp_s - self.memory_s - 1e-9
            or self._travelled_m[drop_first] < travelled_m - self.memory_m
        ):
            drop_first += 1
        first, last = sum(self._counts[:drop_first]), sum(self._counts[:kept])
        self._keep_points(np.vstack((self._points[first:last], np.asarray(points_xy, dtype=np.float64).reshape(-1, 2))))
        self._stamps_s = [*self._stamps_s[drop_first:kept], stamp_s]
        self._travelled_m = [*self._travelled_m[drop_first:kept], travelled_m]
        self._counts = [*self._counts[drop_first:kept], int(self._points.shape[0] - (last - first))]
        self._covariances = np.concatenate((self._covariances[drop_first:kept], np.zeros((1, 2, 2))))

    def points_xy(self) -> FloatArray:
        """Every remembered return, oldest scan first (the memory's own array, read-only)."""
        return self._points

    def _keep_points(self, points_xy: FloatArray) -> None:
        """Hold a new array of points: read-only, since :meth:`points_xy` hands it out."""
        points_xy.flags.writeable = False
        self._points = points_xy

    def sigmas_m(self) -> FloatArray:
        """How far off each of :meth:`points_xy` may lie by now (one standard deviation, along its
        worst axis): the drift since its scan that no alignment took out (0 without alignment)."""
        if not self._counts:
            return np.zeros(0)
        worst = np.sqrt(np.maximum(0.0, np.linalg.eigvalsh(self._covariances)[:, -1]))
        return np.repeat(worst, self._counts)

    def newest_count(self) -> int:
        """How many of :meth:`points_xy` (the last ones) are the newest scan's."""
        return self._counts[-1] if self._counts else 0

    def shift(self, correction: Pose2) -> None:
        """Re-express the points after an estimator reset (``new = correction ∘ old``)."""
        self._keep_points(correction.apply(self._points))

    def align(self, scan: DepthScan, sensor: Pose2, travelled_m: float, no_return_margin_m: float) -> Pose2 | None:
        """Move the remembered returns onto ``scan`` (taken at ``sensor``, not yet added) where its
        walls show where they lie now (see the module's docstring). Every scan is aligned, so the
        memory is one piece, in line with the last; what the walls do not fix adds to how far
        off the memory may lie (:meth:`sigmas_m`). Returns the motion applied (odometry frame),
        or None when none was: too few remembered returns on its walls to tell."""
        p = self.align_params
        if not p.enabled or not self._counts:
            return None
        travel_root = math.sqrt(max(0.0, travelled_m - self._travelled_m[-1]))
        sigma_xy_m = p.min_sigma_xy_m + p.drift_xy_m_per_sqrt_m * travel_root
        sigma_yaw_rad = p.min_sigma_yaw_rad + p.drift_yaw_rad_per_sqrt_m * travel_root
        pts = self._points
        seen = pts[in_view(scan, sensor, pts)]
        # In the sensor's frame: a heading error swings the memory about where the vehicle is.
        local = sensor.inverse()
        found = None
        if seen.shape[0] >= p.min_inliers:
            walls = scan_walls(scan, no_return_margin_m, p.wall_max_gap_m)
            found = align_to_walls(local.apply(seen), walls, sigma_xy_m, sigma_yaw_rad, p)
        if found is None:
            covariance = np.diag([sigma_xy_m**2, sigma_xy_m**2, sigma_yaw_rad**2])
        else:
            covariance = found.covariance
        # The heading's share at the lever a return beside the vehicle has; turned into the
        # odometry frame's axes.
        co, si = math.cos(sensor.yaw_rad), math.sin(sensor.yaw_rad)
        turn = np.array([[co, -si], [si, co]])
        added = turn @ covariance[:2, :2] @ turn.T + covariance[2, 2] * p.lever_m**2 * np.eye(2)
        self._covariances = self._covariances + added
        if found is None:
            return None
        motion = sensor.compose(found.motion).compose(local)
        self.shift(motion)
        return motion

    def forget_seen(self, scan: DepthScan, sensor: Pose2) -> None:
        """Forget the earlier scans' points that ``scan`` (the newest, taken at ``sensor``) has
        its own say about (:func:`in_view`): drift moves old returns a little, and where the
        sensor looks now it is the authority. What stays is out of its view (or seen through
        within ``margin_m`` of its edge), or its own points (when it was added already: it is
        the newest kept, at its stamp)."""
        pts = self.points_xy()
        added = bool(self._stamps_s) and self._stamps_s[-1] == scan.stamp_s
        older = pts.shape[0] - (self.newest_count() if added else 0)
        covered = in_view(scan, sensor, pts[:older], self.margin_m)
        if covered.any():
            self.keep(np.concatenate((~covered, np.ones(pts.shape[0] - older, dtype=bool))))

    def keep(self, mask: NDArray[np.bool_]) -> None:
        """Forget the points whose entry in ``mask`` (one per point of :meth:`points_xy`) is False;
        a scan left with none is dropped, the newest kept (see :meth:`newest_count`)."""
        if not self._counts:
            return
        ends = np.cumsum(self._counts)
        kept_before = np.concatenate(([0], np.cumsum(mask)))
        counts = kept_before[ends] - kept_before[ends - np.asarray(self._counts, dtype=np.intp)]
        stays = counts > 0
        stays[-1] = True
        self._keep_points(self._points[mask])
        self._stamps_s = [v for v, ok in zip(self._stamps_s, stays, strict=True) if ok]
        self._travelled_m = [v for v, ok in zip(self._travelled_m, stays, strict=True) if ok]
        self._counts = [int(c) for c in counts[stays]]
        self._covariances = self._covariances[stays]
