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
from numpy.typing import NDArray

from companion.core.fov_polygon import KIND_OBSTACLE, FovPolygon
from companion.core.geometry import FloatArray, Pose2, Segments, wrap_angle


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
    return _icp(points_xy, walls, guess, params or ScanMatchParams(), None)


def enough_pairs(points_xy: FloatArray, walls: FloatArray, guess: Pose2, params: ScanMatchParams | None = None) -> bool:
    """Whether :func:`match_to_walls` from ``guess`` gets past its first iteration: at least
    ``min_inliers`` of the points within ``start_gate_m`` of a wall (the same nearest-wall
    distances it pairs by). A cheap test of a candidate before the match's iterations."""
    p = params or ScanMatchParams()
    if points_xy.shape[0] < p.min_inliers or walls.shape[0] == 0:
        return False
    dist = _WallTable.of(walls).nearest(guess.apply(points_xy))[0]
    return int(np.count_nonzero(dist < p.start_gate_m)) >= p.min_inliers


def match_with_prior(
    points_xy: FloatArray,
    walls: FloatArray,
    guess: Pose2,
    prior_sigma_xy_m: float,
    prior_sigma_yaw_rad: float,
    params: ScanMatchParams | None = None,
) -> tuple[Pose2, FloatArray, FloatArray] | None:
    """:func:`match_to_walls` weighed against ``guess`` as a prior (the source frame's origin
    within ``prior_sigma_xy_m`` per axis, its heading within ``prior_sigma_yaw_rad``; the
    returns' own spread is ``params.inlier_m / 2``): where the walls fix the pose the returns
    decide, where they fix nothing (along a corridor) the guess stays. A return past a wall's end
    does not pair, and each weighs 1 / (1 + (r / spread)^2): two views' simplified walls differ
    by a few centimetres, and those few returns would otherwise pull the pose. Returns as
    :func:`match_to_walls` does."""
    sigmas = np.array([prior_sigma_xy_m, prior_sigma_xy_m, prior_sigma_yaw_rad])
    return _icp(points_xy, walls, guess, params or ScanMatchParams(), sigmas)


def _icp(
    points_xy: FloatArray, walls: FloatArray, guess: Pose2, p: ScanMatchParams, prior_sigmas: FloatArray | None
) -> tuple[Pose2, FloatArray, FloatArray] | None:
    """The iterations of :func:`match_to_walls` (``prior_sigmas`` None) and
    :func:`match_with_prior` (the prior's sigmas for x, y and yaw)."""
    if points_xy.shape[0] < p.min_inliers or walls.shape[0] == 0:
        return None
    sigma_scan_m = 0.5 * p.inlier_m
    pose, gate = guess, p.start_gate_m
    # Only the walls the points could pair with: within the first gate of their bounding box.
    moved = pose.apply(points_xy)
    lo, hi = moved.min(axis=0) - gate, moved.max(axis=0) + gate
    walls = walls[np.all((walls.max(axis=1) >= lo) & (walls.min(axis=1) <= hi), axis=1)]
    if walls.shape[0] == 0:
        return None
    near_walls = _WallTable.of(walls)
    for _ in range(p.max_iterations):
        dist, closest, normals, at_end = near_walls.nearest(moved)
        use = dist < gate
        if prior_sigmas is not None:
            # A return past a wall's end (the other view saw that wall less far) says nothing of
            # where along the wall it lies; pulled to the end, it would shorten every corridor.
            use &= ~at_end
        if int(np.count_nonzero(use)) < p.min_inliers:
            return None
        prior = None if prior_sigmas is None else (pose, guess, prior_sigmas**-2 * sigma_scan_m**2)
        robust_m = None if prior_sigmas is None else sigma_scan_m
        step = solve_step(moved[use], closest[use], normals[use], prior, robust_m)
        pose = step.compose(pose)
        moved = pose.apply(points_xy)
        gate = max(p.final_gate_m, p.gate_shrink * gate)
        if math.hypot(step.x_m, step.y_m) < 1e-3 and abs(step.yaw_rad) < 1e-4 and gate <= p.final_gate_m:
            break
    dist, _, normals, _ = near_walls.nearest(moved)
    return pose, dist, normals


def fit_cost(points_xy: FloatArray, walls: FloatArray, pose: Pose2, truncate_m: float) -> float:
    """How badly ``points_xy`` (source frame) placed at ``pose`` fit ``walls``: the mean squared
    distance to the nearest wall, each capped at ``truncate_m`` (a return off every wall counts
    the same however far off), over the returns not past a wall's end."""
    if points_xy.shape[0] == 0 or walls.shape[0] == 0:
        return truncate_m**2
    dist, _, _, at_end = _WallTable.of(walls).nearest(pose.apply(points_xy))
    capped = np.minimum(dist[~at_end], truncate_m)
    return float(np.mean(capped**2)) if capped.size else truncate_m**2


def view_points(polygon: FovPolygon, walls: FloatArray, spacing_m: float) -> FloatArray:
    """A view's walls (``walls``, its obstacle edges (M, 2, 2)) as points about ``spacing_m``
    apart, from each wall's first end, and its obstacle vertices, in its frame: a match then
    weighs walls by length, not by how many vertices the view's simplification left on them."""
    corners = np.asarray(polygon.vertices_xy[polygon.kinds == KIND_OBSTACLE], dtype=np.float64).reshape(-1, 2)
    if walls.shape[0] == 0:
        return corners
    a, b = walls[:, 0, :], walls[:, 1, :]
    counts = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing_m).astype(np.intp))
    owner = np.repeat(np.arange(walls.shape[0]), counts)
    starts = np.cumsum(counts) - counts
    t = (np.arange(owner.size) - starts[owner]) / counts[owner]
    along = a[owner] + t[:, None] * (b - a)[owner]
    return np.asarray(np.vstack((along, corners)), dtype=np.float64)


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


@dataclass(frozen=True, slots=True)
class _WallTable:
    """Walls ((M, 2, 2)) as each nearest-wall search needs them: a match asks the same walls
    for every iteration's points, so what depends on the walls alone is computed once."""

    segments: Segments
    normals: FloatArray  # (M, 2): unit normals

    @classmethod
    def of(cls, walls: FloatArray) -> _WallTable:
        segments = Segments.of(walls)
        along_x, along_y = segments.along_x[0], segments.along_y[0]
        normals = np.column_stack((-along_y, along_x))
        normals /= np.maximum(np.sqrt(along_x * along_x + along_y * along_y), 1e-12)[:, None]
        return cls(segments, normals)

    def nearest(self, points_xy: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_]]:
        """Each point's distance to its nearest wall, the nearest point on it, and the wall's unit
        normal (the direction from that point when it is a wall's end: the residual is a
        distance), and whether that nearest point is a wall's end."""
        cx, cy, t_all = self.segments.closest(points_xy)
        ox, oy = points_xy[:, 0:1] - cx, points_xy[:, 1:2] - cy
        squared = ox * ox + oy * oy  # the square root only of the nearest
        j = np.argmin(squared, axis=1)
        rows = np.arange(points_xy.shape[0])
        dist = np.sqrt(squared[rows, j])
        closest = np.empty_like(points_xy)
        closest[:, 0], closest[:, 1] = cx[rows, j], cy[rows, j]
        normals = self.normals[j]
        t = t_all[rows, j]
        at_end = (t <= 0.0) | (t >= 1.0)
        far = at_end & (dist > 1e-9)
        if far.any():
            normals[far] = (points_xy[far] - closest[far]) / dist[far, None]
        return dist, closest, normals, at_end


def solve_step(
    points_xy: FloatArray,
    closest_xy: FloatArray,
    normals: FloatArray,
    prior: tuple[Pose2, Pose2, FloatArray] | None = None,
    robust_m: float | None = None,
) -> Pose2:
    """The rigid motion (in the target frame) that best moves ``points_xy`` onto the lines
    through ``closest_xy`` with ``normals``: linearised about the points' centroid, least squares.
    ``prior = (pose, guess, weights)`` also pulls the source origin and heading (now at
    ``pose``) back towards ``guess``, each axis weighed as the scan's residuals are; with
    ``robust_m`` each residual r weighs 1 / (1 + (r / robust_m)^2) (Cauchy)."""
    c = np.add.reduce(points_xy, axis=0) / points_xy.shape[0]  # the mean, without np.mean's overhead
    rel = points_xy - c
    jac = np.empty((points_xy.shape[0], 3))
    jac[:, :2] = normals
    jac[:, 2] = normals[:, 1] * rel[:, 0] - normals[:, 0] * rel[:, 1]  # n . perp(p - c)
    gap = points_xy - closest_xy
    resid = normals[:, 0] * gap[:, 0] + normals[:, 1] * gap[:, 1]
    w = np.ones_like(resid) if robust_m is None else 1.0 / (1.0 + (resid / robust_m) ** 2)
    lhs, rhs = jac.T @ (w[:, None] * jac) + 1e-9 * np.eye(3), -jac.T @ (w * resid)
    if prior is not None:
        pose, guess, weights = prior
        # The step moves the origin o by t + dyaw * perp(o - c), and the heading by dyaw.
        ox, oy = pose.x_m - c[0], pose.y_m - c[1]
        a = np.array([[1.0, 0.0, -oy], [0.0, 1.0, ox], [0.0, 0.0, 1.0]])
        off = np.array([pose.x_m - guess.x_m, pose.y_m - guess.y_m, wrap_angle(pose.yaw_rad - guess.yaw_rad)])
        lhs += a.T @ (weights[:, None] * a)
        rhs -= a.T @ (weights * off)
    delta = np.linalg.solve(lhs, rhs)
    tx, ty, dyaw = delta.tolist()
    co, si = math.cos(dyaw), math.sin(dyaw)
    # p -> c + R (p - c) + t  ==  R p + (c - R c + t)
    return Pose2(c[0] - (co * c[0] - si * c[1]) + tx, c[1] - (si * c[0] + co * c[1]) + ty, dyaw)
