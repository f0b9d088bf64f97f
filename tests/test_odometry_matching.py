"""Scan-matched odometry edges: the walls fix what they can, the odometry the rest."""

import itertools
import math

import numpy as np

from companion.core.explorer import Explorer, ExplorerParams, _bent_to
from companion.core.fov_polygon import scan_to_polygon
from companion.core.geometry import Pose2
from companion.core.local_map import Keyframe
from companion.core.messages import Odometry
from companion.core.odometry_matching import OdometryMatchingParams, match_odometry_edge
from companion.core.scan_matching import match_with_prior
from tests.test_loop_closing import CORNER, ROOM, ROUND, along, scan_at, walls_of

PRIOR_XY_M, PRIOR_YAW_RAD = 0.1, 0.03


def test_where_the_walls_fix_the_pose_they_decide_it():
    true = Pose2(1.0, 0.5, 0.2)
    source = true.inverse().apply(along(CORNER))
    guess = true.compose(Pose2(0.15, -0.1, 0.03))
    aligned = match_with_prior(source, CORNER, guess, PRIOR_XY_M, PRIOR_YAW_RAD)
    assert aligned is not None
    err = true.between(aligned[0])
    assert math.hypot(err.x_m, err.y_m) < 0.01 and abs(err.yaw_rad) < 0.002


def test_along_a_corridor_the_odometry_keeps_what_the_walls_cannot_fix():
    """Two parallel walls fix the heading and the offset across, not the place along; the new
    view also sees 2 m farther than the old one did, and those returns, past the old walls'
    ends, must not pull it back along the corridor."""
    target = walls_of((-3, 0, 5, 0), (-3, 1.2, 5, 1.2))
    seen = walls_of((-1, 0, 7, 0), (-1, 1.2, 7, 1.2))
    true = Pose2(1.0, 0.6, 0.0)
    source = true.inverse().apply(along(seen))
    guess = Pose2(1.2, 0.5, 0.02)  # 0.2 m on along the corridor, 0.1 m across, turned
    aligned = match_with_prior(source, target, guess, PRIOR_XY_M, PRIOR_YAW_RAD)
    assert aligned is not None
    pose = aligned[0]
    assert abs(pose.y_m - true.y_m) < 0.01 and abs(pose.yaw_rad - true.yaw_rad) < 0.002
    assert abs(pose.x_m - guess.x_m) < 0.02  # where the odometry put it along the corridor


def keyframe_at(pose: Pose2, keyframe_id: int = 0) -> Keyframe:
    return Keyframe(keyframe_id, float(keyframe_id), pose, scan_to_polygon(scan_at(pose, ROOM, float(keyframe_id))))


def test_an_edge_between_two_real_views_is_corrected_or_refused():
    parent_pose, child_pose = Pose2(4.0, 3.0, 0.6), Pose2(5.0, 3.5, 0.7)  # facing the room's corner
    parent = keyframe_at(parent_pose)
    polygon = scan_to_polygon(scan_at(child_pose, ROOM, 1.0))
    true = parent_pose.between(child_pose)
    params = OdometryMatchingParams()
    matched = match_odometry_edge(polygon, parent, true.compose(Pose2(0.12, -0.08, 0.03)), params)
    assert matched is not None
    err = true.between(matched)
    assert math.hypot(err.x_m, err.y_m) < 0.03 and abs(err.yaw_rad) < 0.01  # was 0.14 m, 0.03 rad off
    # More than the odometry can be off by (3 sigma of the prior): not taken, whatever it found.
    assert match_odometry_edge(polygon, parent, true.compose(Pose2(0.45, 0.0, 0.0)), params) is None
    # A view of another room does not match this one.
    other = walls_of((0, 0, 5, 0), (5, 0, 5, 5), (5, 5, 0, 5), (0, 5, 0, 0))
    elsewhere = scan_to_polygon(scan_at(Pose2(2.0, 2.0, 0.0), other, 1.0))
    assert match_odometry_edge(elsewhere, parent, true, params) is None


def edge_errors(explorer: Explorer, truth: dict[int, Pose2]) -> np.ndarray:
    """Each odometry edge's error against the true relative pose: metres and radians."""
    out = []
    for k in sorted(truth)[1:]:
        est = explorer.map.pose_in(k - 1, k)
        err = truth[k - 1].between(truth[k]).between(est)
        out.append((math.hypot(err.x_m, err.y_m), abs(err.yaw_rad)))
    return np.array(out)


def test_the_explorer_corrects_drifting_odometry_edge_by_edge():
    """Round the room with odometry that drifts about 4 cm and 0.01 rad per metre, the
    explorer's edges come out at least twice as true with matching as the odometry gave them."""
    path: list[Pose2] = []  # round the room in 0.25 m steps between the waypoints
    for a, b in itertools.pairwise(ROUND):
        for t in np.linspace(0.0, 1.0, 5)[:-1]:
            yaw = a.yaw_rad + t * math.remainder(b.yaw_rad - a.yaw_rad, 2 * math.pi)
            path.append(Pose2(a.x_m + t * (b.x_m - a.x_m), a.y_m + t * (b.y_m - a.y_m), yaw))
    results = {}
    for enabled in (False, True):
        ex = Explorer(ExplorerParams(look_around_rad=0.0, odometry_matching=OdometryMatchingParams(enabled=enabled)))
        rng = np.random.default_rng(3)
        odom = path[0]
        truth: dict[int, Pose2] = {}
        for k, true in enumerate(path):
            if k:
                step = path[k - 1].between(true)
                noise = Pose2(*rng.normal(0.0, [0.02, 0.02, 0.005]))
                odom = odom.compose(step).compose(noise)
            before = set(ex.map.keyframes)
            ex.step(Odometry(0.1 * k, odom), scan_at(true, ROOM, 0.1 * k))
            for new in set(ex.map.keyframes) - before:
                truth[new] = true
        results[enabled] = (edge_errors(ex, truth), ex.odometry_edges_matched, len(truth))
    off, _, kfs = results[False]
    on, matched, _ = results[True]
    assert kfs >= 8 and matched >= kfs // 2  # the rest overlap their parent too little
    assert on[:, 0].mean() < 0.5 * off[:, 0].mean() and on[:, 1].mean() < 0.5 * off[:, 1].mean()


def test_the_way_flown_is_bent_to_end_where_the_match_put_the_keyframe():
    """The way flown between two keyframes (odometry, in the parent's frame) is kept for routes
    back; corrected, the edge ends elsewhere, and the way is bent to end there too: each point
    moved by its share of the correction, the parent's end not at all."""
    flown = np.array([[0.25, 0.0], [0.5, 0.0], [0.75, 0.0]])
    odometry_end, matched_end = Pose2(1.0, 0.0, 0.0), Pose2(1.0, 0.2, 0.1)
    bent = _bent_to(flown, odometry_end, matched_end)
    moved = np.hypot(*(bent - flown).T)
    assert np.all(np.diff(moved) > 0) and moved[0] < 0.08
    # Three quarters of the way to the matched end, near where a straight way to it would be.
    assert math.hypot(bent[2, 0] - 0.75, bent[2, 1] - 0.15) < 0.03
    assert _bent_to(flown, odometry_end, odometry_end) is flown
