"""Scan matching: where one view's obstacle returns lie against another view's walls.

Point-to-line ICP (Censi 2008's metric, solved by linearising the rotation each iteration) of
one keyframe's obstacle vertices onto another's obstacle edges, both 2D and in their own frames.
A match is accepted only when it is good *and* trustworthy: enough returns on the walls, a small
residual, walls facing more than one way (a corridor's two parallel walls fix nothing along
it), and neither view seeing a wall where the other saw free space (a repeated room or door
that fits the walls but not the free space is another place).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely

from companion.core.geometry import FloatArray, Pose2, closest_on_segments


@dataclass(frozen=True, slots=True)
class ScanMatchParams:
    """Tuning for :func:`match_to_walls`."""

    max_iterations: int = 20
    start_gate_m: float = 1.0  # a return pairs with a wall this far at first ...
    final_gate_m: float = 0.2  # ... shrinking to this
    gate_shrink: float = 0.85  # per iteration
    inlier_m: float = 0.06  # a return this close to a wall after the match lies on it
    min_inliers: int = 20  # points on walls (0.15 m apart: 3 m of wall)
    min_inlier_fraction: float = 0.8  # of the points near its walls
    max_rms_m: float = 0.04  # of the inliers' distances
    # The smallest eigenvalue of the inliers' wall normals' scatter (0 for one straight wall or a
    # corridor, 0.5 for walls facing every way equally): the match must be fixed along both axes.
    min_constraint: float = 0.15
    contradiction_depth_m: float = 0.2  # a return this deep inside the other view's free space ...
    max_contradiction_fraction: float = 0.03  # ... contradicts it; this many of them reject the match


@dataclass(frozen=True, slots=True)
class ScanMatch:
    """An accepted match: ``pose`` is the source view's frame in the target view's frame."""

    pose: Pose2
    inliers: int
    rms_m: float
    constraint: float
    weak_axis: tuple[float, float]  # the direction the walls fix least (unit, target frame)


def match_to_walls(
    points_xy: FloatArray,
    walls: FloatArray,
    guess: Pose2,
    params: ScanMatchParams | None = None,
) -> tuple[Pose2, FloatArray, FloatArray] | None:
    """Align ``points_xy`` (source frame) to ``walls`` ((M, 2, 2), target frame) from ``guess``
    (source in target). Returns the pose, each point's distance to its nearest wall and that
    wall's unit normal, or None when too few points ever pair with a wall."""
    p = params or ScanMatchParams()
    if points_xy.shape[0] < p.min_inliers or walls.shape[0] == 0:
        return None
    pose = guess
    gate = p.start_gate_m
    # Only the walls the points could pair with: within the first gate of their bounding box.
    moved = pose.apply(points_xy)
    lo, hi = moved.min(axis=0) - gate, moved.max(axis=0) + gate
    ends_lo, ends_hi = walls.min(axis=1), walls.max(axis=1)
    walls = walls[np.all((ends_hi >= lo) & (ends_lo <= hi), axis=1)]
    if walls.shape[0] == 0:
        return None
    for _ in range(p.max_iterations):
        dist, closest, normals = _nearest_on_walls(moved, walls)
        use = dist < gate
        if int(np.count_nonzero(use)) < p.min_inliers:
            return None
        step = _solve_step(moved[use], closest[use], normals[use])
        pose = step.compose(pose)
        moved = pose.apply(points_xy)
        gate = max(p.final_gate_m, p.gate_shrink * gate)
        if math.hypot(step.x_m, step.y_m) < 1e-3 and abs(step.yaw_rad) < 1e-4 and gate <= p.final_gate_m:
            break
    dist, _, normals = _nearest_on_walls(moved, walls)
    return pose, dist, normals


def accept_match(
    source_points_xy: FloatArray,
    source_view: shapely.Geometry,
    target_points_xy: FloatArray,
    target_view: shapely.Geometry,
    aligned: tuple[Pose2, FloatArray, FloatArray],
    params: ScanMatchParams | None = None,
) -> ScanMatch | None:
    """Judge an alignment from :func:`match_to_walls`: None unless the source's returns inside the
    target's view lie on its walls, they fix the pose along both axes, and neither view's returns
    lie deep in the other's free space."""
    p = params or ScanMatchParams()
    pose, dist, normals = aligned
    moved = pose.apply(source_points_xy)
    inlier = dist < p.inlier_m
    n_in = int(np.count_nonzero(inlier))
    # Those near its walls should lie on them (those deep in its free space are judged below).
    near = int(np.count_nonzero(dist < p.contradiction_depth_m))
    if n_in < p.min_inliers or n_in < p.min_inlier_fraction * near:
        return None
    rms = float(np.sqrt(np.mean(dist[inlier] ** 2)))
    if rms > p.max_rms_m:
        return None
    scatter = normals[inlier].T @ normals[inlier] / n_in
    eigenvalues, eigenvectors = np.linalg.eigh(scatter)
    constraint = float(eigenvalues[0])
    if constraint < p.min_constraint:
        return None
    back = pose.inverse().apply(target_points_xy)
    if _contradicted(moved, target_view, p) or _contradicted(back, source_view, p):
        return None
    return ScanMatch(pose, n_in, rms, constraint, (float(eigenvectors[0, 0]), float(eigenvectors[1, 0])))


def _contradicted(points_xy: FloatArray, view: shapely.Geometry, p: ScanMatchParams) -> bool:
    """Whether too many of ``points_xy`` (returns) lie deep inside ``view``'s free space."""
    if points_xy.shape[0] == 0:
        return False
    inside = np.asarray(shapely.contains_xy(view, points_xy[:, 0], points_xy[:, 1]), dtype=bool)
    if not inside.any():
        return False
    depth = np.asarray(shapely.distance(view.exterior, shapely.points(points_xy[inside])), dtype=np.float64)
    deep = int(np.count_nonzero(depth > p.contradiction_depth_m))
    return bool(deep > p.max_contradiction_fraction * points_xy.shape[0])


def _nearest_on_walls(points_xy: FloatArray, walls: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each point's distance to its nearest wall, the nearest point on it, and the wall's unit
    normal (the direction from that point when it is a wall's end: the residual is a distance)."""
    closest_all, t = closest_on_segments(points_xy, walls)
    d_all = np.linalg.norm(points_xy[:, None, :] - closest_all, axis=2)
    j = np.argmin(d_all, axis=1)
    rows = np.arange(points_xy.shape[0])
    dist = d_all[rows, j]
    closest = closest_all[rows, j]
    seg = walls[j, 1, :] - walls[j, 0, :]
    normals = np.column_stack((-seg[:, 1], seg[:, 0])) / np.maximum(np.linalg.norm(seg, axis=1), 1e-12)[:, None]
    at_end = (t[rows, j] <= 0.0) | (t[rows, j] >= 1.0)
    off = points_xy - closest
    far = at_end & (dist > 1e-9)
    normals[far] = off[far] / dist[far, None]
    return np.asarray(dist, dtype=np.float64), np.asarray(closest, dtype=np.float64), normals


def _solve_step(points_xy: FloatArray, closest_xy: FloatArray, normals: FloatArray) -> Pose2:
    """The rigid motion (in the target frame) that best moves ``points_xy`` onto the lines
    through ``closest_xy`` with ``normals``: linearised about the points' centroid, least squares."""
    c = points_xy.mean(axis=0)
    rel = points_xy - c
    lever = normals[:, 1] * rel[:, 0] - normals[:, 0] * rel[:, 1]  # n . perp(p - c)
    jac = np.column_stack((normals, lever))
    resid = np.einsum("nk,nk->n", normals, points_xy - closest_xy)
    delta = np.linalg.solve(jac.T @ jac + 1e-9 * np.eye(3), -jac.T @ resid)
    tx, ty, dyaw = (float(v) for v in delta)
    co, si = math.cos(dyaw), math.sin(dyaw)
    # p -> c + R (p - c) + t  ==  R p + (c - R c + t)
    return Pose2(c[0] - (co * c[0] - si * c[1]) + tx, c[1] - (si * c[0] + co * c[1]) + ty, dyaw)
