"""Scan-matched odometry edges: each new keyframe's edge to its parent, as odometry gives it,
corrected by aligning the new view's walls onto the parent's.

Odometry drifts with every metre flown, and the map sees that drift wherever it places one view
in another's frame along the graph: a wall two views saw lies 0.2-0.4 m apart at a few hops with
the thesis's drift, too far for a frontier on it to be recognised as lying on a wall, and the
vehicle flies back at the end to look at it. Consecutive views overlap almost wholly, so their
walls fix the relative pose far better than the odometry between them, except along a straight
corridor, where they fix nothing along it. So the match weighs the odometry as a prior
(:func:`match_with_prior`): the walls decide where they can, the odometry where they cannot.
The edge stays a relative transform between two keyframes; nothing else changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from companion.core.fov_polygon import FovPolygon
from companion.core.geometry import Pose2
from companion.core.local_map import Keyframe
from companion.core.scan_matching import ScanMatchParams, accept_match, fit_cost, match_with_prior, view_points


def _edge_match_params() -> ScanMatchParams:
    # Consecutive views start close (one keyframe's odometry error), so the first gate is
    # narrower than a loop closure's; the prior, not the walls' spread, fixes a corridor's axis.
    return ScanMatchParams(
        max_iterations=10, start_gate_m=0.5, final_gate_m=0.15, gate_shrink=0.7, min_inliers=20, min_constraint=0.0
    )


@dataclass(frozen=True, slots=True)
class OdometryMatchingParams:
    """Tuning for :func:`match_odometry_edge`."""

    enabled: bool = True
    # How far the odometry between two keyframes may be off (one sigma): the prior's weight.
    prior_sigma_xy_m: float = 0.1
    prior_sigma_yaw_rad: float = 0.03
    # A correction beyond this many sigmas of the prior on any axis is a match gone astray.
    max_correction_sigmas: float = 3.0
    # The match's fit (see fit_cost) must be at most this fraction of the odometry pose's.
    min_fit_gain: float = 0.5
    point_spacing_m: float = 0.15  # the walls are matched as points this far apart
    match: ScanMatchParams = field(default_factory=_edge_match_params)


def match_odometry_edge(
    polygon: FovPolygon, parent: Keyframe, guess: Pose2, params: OdometryMatchingParams
) -> Pose2 | None:
    """The new view's (``polygon``'s) frame in ``parent``'s, corrected from the odometry's
    ``guess`` by matching its walls to the parent's; None when the match is not trusted (too
    few returns on the parent's walls, a poor fit, a contradiction, or a correction the
    odometry cannot have needed)."""
    source = view_points(polygon, polygon.obstacle_segments(), params.point_spacing_m)
    aligned = match_with_prior(
        source, parent.walls, guess, params.prior_sigma_xy_m, params.prior_sigma_yaw_rad, params.match
    )
    if aligned is None:
        return None
    target = view_points(parent.polygon, parent.walls, params.point_spacing_m)
    match = accept_match(source, polygon.shape, target, parent.polygon.shape, aligned, params.match)
    if match is None:
        return None
    # Taken only when it fits clearly better than the odometry's pose: where the odometry was
    # right already, a view's walls can still slide a little along themselves at no cost.
    truncate = params.match.final_gate_m
    fit = fit_cost(source, parent.walls, match.pose, truncate)
    if fit > params.min_fit_gain * fit_cost(source, parent.walls, guess, truncate):
        return None
    moved = guess.between(match.pose)
    limit = params.max_correction_sigmas
    if max(abs(moved.x_m), abs(moved.y_m)) > limit * params.prior_sigma_xy_m:
        return None
    if abs(moved.yaw_rad) > limit * params.prior_sigma_yaw_rad:
        return None
    return match.pose
