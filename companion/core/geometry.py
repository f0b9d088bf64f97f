"""SE(2) poses and transforms in the core's frame: x forward/east, y left/north, yaw CCW from x."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import shapely
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
GeometryT = TypeVar("GeometryT", bound=shapely.Geometry)


def wrap_angle(angle_rad: float) -> float:
    """Wrap an angle to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def wrap_angles(angles_rad: FloatArray) -> FloatArray:
    """Vectorised :func:`wrap_angle`."""
    return np.asarray((angles_rad + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


@dataclass(frozen=True, slots=True)
class Pose2:
    """A rigid transform in the plane; as a pose, where a frame sits in its parent frame."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0

    @staticmethod
    def identity() -> Pose2:
        return Pose2(0.0, 0.0, 0.0)

    def is_finite(self) -> bool:
        return math.isfinite(self.x_m) and math.isfinite(self.y_m) and math.isfinite(self.yaw_rad)

    def compose(self, other: Pose2) -> Pose2:
        """``self ∘ other``: ``other`` given in ``self``'s frame, lifted to ``self``'s parent."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return Pose2(
            self.x_m + c * other.x_m - s * other.y_m,
            self.y_m + s * other.x_m + c * other.y_m,
            wrap_angle(self.yaw_rad + other.yaw_rad),
        )

    def __matmul__(self, other: Pose2) -> Pose2:
        return self.compose(other)

    def inverse(self) -> Pose2:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return Pose2(
            -(c * self.x_m + s * self.y_m),
            -(-s * self.x_m + c * self.y_m),
            wrap_angle(-self.yaw_rad),
        )

    def between(self, other: Pose2) -> Pose2:
        """The transform from this pose to ``other``: ``self⁻¹ ∘ other``."""
        return self.inverse().compose(other)

    def apply(self, points_xy: FloatArray) -> FloatArray:
        """Map an (N, 2) array of points from this frame into its parent frame."""
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        out = np.empty_like(pts)
        out[:, 0] = c * pts[:, 0] - s * pts[:, 1] + self.x_m
        out[:, 1] = s * pts[:, 0] + c * pts[:, 1] + self.y_m
        return out

    def apply_point(self, x_m: float, y_m: float) -> tuple[float, float]:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return (c * x_m - s * y_m + self.x_m, s * x_m + c * y_m + self.y_m)

    def rotate(self, vectors_xy: FloatArray) -> FloatArray:
        """Rotate (N, 2) direction vectors into the parent frame (no translation)."""
        v = np.asarray(vectors_xy, dtype=np.float64).reshape(-1, 2)
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return np.column_stack((c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]))

    def move(self, geometry: GeometryT) -> GeometryT:
        """Map a shapely geometry from this frame into its parent frame (every coordinate through
        :meth:`apply` at once: twice as fast as ``shapely.affinity``, the same numbers)."""
        moved: GeometryT = shapely.transform(geometry, self.apply)
        return moved

    def distance_to(self, other: Pose2) -> float:
        return math.hypot(other.x_m - self.x_m, other.y_m - self.y_m)


def apply_each(poses: list[Pose2] | FloatArray, points_xy: FloatArray, owner: NDArray[np.intp]) -> FloatArray:
    """Map each point through the pose of its owner (``points_xy[i]`` through ``poses[owner[i]]``)
    in one vectorised pass: many keyframes' points into one frame at once. ``poses`` may also be
    rows of ``x_m, y_m, yaw_rad`` (as :class:`~companion.core.pose_graph.Reached` holds them)."""
    if isinstance(poses, np.ndarray):
        rows = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    else:
        rows = np.array([(p.x_m, p.y_m, p.yaw_rad) for p in poses], dtype=np.float64).reshape(-1, 3)
    # The turn's cosine and sine once per pose, not per point (the same numbers).
    c, s = np.cos(rows[:, 2])[owner], np.sin(rows[:, 2])[owner]
    x, y = points_xy[:, 0], points_xy[:, 1]
    return np.column_stack((c * x - s * y + rows[owner, 0], s * x + c * y + rows[owner, 1]))


def apply_grouped(poses: list[Pose2] | FloatArray, groups: list[FloatArray]) -> FloatArray:
    """Map each (N_j, 2) group of points through ``poses[j]``, all groups stacked in one array
    (``poses`` as :func:`apply_each` takes them)."""
    owner = np.repeat(np.arange(len(groups)), [g.shape[0] for g in groups])
    return apply_each(poses, np.vstack(groups).reshape(-1, 2), owner)


def move_each(poses: list[Pose2] | FloatArray, geometries: NDArray[np.object_]) -> NDArray[np.object_]:
    """Map ``geometries[i]`` through ``poses[i]`` (copies; one shapely call for all of them, where
    :meth:`Pose2.move` in a loop costs a call per geometry; ``poses`` as :func:`apply_each` takes
    them)."""
    _, owner = shapely.get_coordinates(geometries, return_index=True)
    moved: NDArray[np.object_] = shapely.transform(geometries, lambda xy: apply_each(poses, xy, owner))
    return moved


@dataclass(frozen=True, slots=True)
class Segments:
    """M segments, given as (M, 2, 2), held as each closest-point query needs them: a caller
    asking the same segments many times (a scan match's iterations) computes them once. x and y
    are kept apart, each (1, M): numpy's products and sums over an axis of two (a point's x and
    y) copy through buffers and cost several times the arithmetic (the same bits either way)."""

    start_x: FloatArray  # each segment's first end
    start_y: FloatArray
    along_x: FloatArray  # from its first end to its second
    along_y: FloatArray
    length_sq: FloatArray  # ``along``'s squared length, at least 1e-12

    @classmethod
    def of(cls, segments: FloatArray) -> Segments:
        ax, ay = segments[None, :, 0, 0], segments[None, :, 0, 1]
        abx, aby = segments[None, :, 1, 0] - ax, segments[None, :, 1, 1] - ay
        return cls(ax, ay, abx, aby, np.maximum(abx * abx + aby * aby, 1e-12))

    def closest(self, points_xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """For N points: the x and y of the closest point of each segment to each point, and
        where along the segment it lies, in [0, 1]; each (N, M)."""
        px, py = points_xy[:, 0:1], points_xy[:, 1:2]
        t = ((px - self.start_x) * self.along_x + (py - self.start_y) * self.along_y) / self.length_sq
        np.minimum(np.maximum(t, 0.0, out=t), 1.0, out=t)
        return self.start_x + t * self.along_x, self.start_y + t * self.along_y, t


def closest_on_segments(points_xy: FloatArray, segments: FloatArray) -> tuple[FloatArray, FloatArray]:
    """For N points and M segments given as (M, 2, 2): the (N, M, 2) closest point of each
    segment to each point, and where along the segment it lies, (N, M) in [0, 1]."""
    cx, cy, t = Segments.of(segments).closest(points_xy)
    return np.stack((cx, cy), axis=2), t


def point_segment_distances(points_xy: FloatArray, segments: FloatArray) -> FloatArray:
    """(N, M) distances from N points to M segments given as (M, 2, 2)."""
    cx, cy, _ = Segments.of(segments).closest(points_xy)
    ox, oy = points_xy[:, 0:1] - cx, points_xy[:, 1:2] - cy
    return np.asarray(np.sqrt(ox * ox + oy * oy), dtype=np.float64)


def first_contact(
    points_xy: FloatArray, direction_xy: tuple[float, float], radius_m: float | FloatArray
) -> tuple[float, int]:
    """How far a disc of ``radius_m`` at the origin can move along ``direction_xy`` before it
    touches one of the points, and which one it touches first ((inf, -1) when none is in its way).
    ``radius_m`` may be one per point (a berth each)."""
    dx, dy = direction_xy
    norm = math.hypot(dx, dy)
    if norm < 1e-9 or points_xy.shape[0] == 0:
        return math.inf, -1
    along = (points_xy[:, 0] * dx + points_xy[:, 1] * dy) / norm
    across = np.abs(points_xy[:, 1] * dx - points_xy[:, 0] * dy) / norm
    hit = (along > 0.0) & (across < radius_m)
    if not hit.any():
        return math.inf, -1
    travel = np.where(hit, along - np.sqrt(np.maximum(radius_m**2 - across**2, 0.0)), np.inf)
    i = int(np.argmin(travel))
    return max(0.0, float(travel[i])), i
