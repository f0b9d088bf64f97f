"""The companion's own loop closures: scan matching and the search over old keyframes."""

import itertools
import math

import numpy as np
import pytest
import shapely

import companion.core.loop_closing as loop_closing
from companion.core.explorer import Explorer, ExplorerParams
from companion.core.fov_polygon import scan_to_polygon
from companion.core.geometry import Pose2
from companion.core.local_map import LocalMap
from companion.core.loop_closing import LoopClosingParams, ViewMatcher
from companion.core.messages import DepthScan, Odometry
from companion.core.pose_graph import EdgeType
from companion.core.scan_matching import ScanMatch, accept_match, enough_pairs, match_to_walls
from sitl.depth_sensor import SensorParams, cast_rays


def walls_of(*segments: tuple[float, float, float, float]) -> np.ndarray:
    return np.array([[[x0, y0], [x1, y1]] for x0, y0, x1, y1 in segments], dtype=float)


def along(walls: np.ndarray, spacing_m: float = 0.1) -> np.ndarray:
    """Points along each wall, ``spacing_m`` apart."""
    out = []
    for (x0, y0), (x1, y1) in walls:
        n = max(1, int(math.hypot(x1 - x0, y1 - y0) / spacing_m))
        t = np.arange(n) / n
        out.append(np.column_stack((x0 + t * (x1 - x0), y0 + t * (y1 - y0))))
    return np.vstack(out)


CORNER = walls_of((0, 0, 4, 0), (0, 0, 0, 3), (4, 0, 4, 1))  # two walls meeting, a third stub
CORRIDOR = walls_of((-3, 0, 5, 0), (-3, 1.2, 5, 1.2))  # two parallel walls: nothing fixes the x
ROOM_VIEW = shapely.box(0, 0, 4, 3)  # what a view of CORNER saw free


def test_a_view_is_matched_back_from_a_guess_half_a_metre_off():
    true = Pose2(1.0, 0.5, 0.2)  # the source's frame in the target's
    source = true.inverse().apply(along(CORNER))
    aligned = match_to_walls(source, CORNER, Pose2(1.4, 0.2, 0.3))
    assert aligned is not None
    source_view = true.inverse().move(ROOM_VIEW)
    match = accept_match(source, source_view, along(CORNER), ROOM_VIEW, aligned)
    assert match is not None
    err = true.between(match.pose)
    assert math.hypot(err.x_m, err.y_m) < 0.01 and abs(err.yaw_rad) < 0.002


def test_a_corridor_fixes_nothing_along_it_and_is_not_taken():
    true = Pose2(1.0, 0.3, 0.0)
    seen = walls_of((-1, 0, 3, 0), (-1, 1.2, 3, 1.2))  # a stretch of it, no wall's end
    source = true.inverse().apply(along(seen))
    aligned = match_to_walls(source, CORRIDOR, Pose2(1.5, 0.35, 0.05))
    assert aligned is not None
    pose, dist, _ = aligned
    assert np.max(dist) < 0.01  # it fits perfectly, where the guess had it along the corridor ...
    assert abs(pose.x_m - true.x_m) > 0.3
    view = shapely.box(-3, 0, 5, 1.2)
    # ... but slid along the corridor, so the match is refused, not trusted.
    assert accept_match(source, true.inverse().move(view), along(CORRIDOR), view, aligned) is None


def test_a_view_that_sees_a_wall_where_the_other_saw_free_space_is_not_taken():
    true = Pose2(0.5, 0.5, 0.0)
    across = walls_of((1.0, 1.5, 3.5, 1.5))  # a wall through the middle of what the target saw free
    for extra, taken in ((np.zeros((0, 2, 2)), True), (across, False)):
        source = true.inverse().apply(along(np.concatenate((CORNER, extra))))
        aligned = match_to_walls(source, CORNER, true)
        assert aligned is not None
        source_view = true.inverse().move(shapely.box(0, 0, 4, 1.4))
        match = accept_match(source, source_view, along(CORNER), ROOM_VIEW, aligned)
        assert (match is not None) is taken


# -- the search over the map's keyframes --------------------------------------------------------

ROOM = walls_of(
    (0, 0, 8, 0), (8, 0, 8, 6), (8, 6, 0, 6), (0, 6, 0, 0),  # an 8 x 6 m room
    (5, 2, 6, 2), (6, 2, 6, 3), (6, 3, 5, 3), (5, 3, 5, 2),  # a pillar
    (0, 4, 2, 4),  # a wall stub
)  # fmt: skip


def scan_at(pose: Pose2, walls: np.ndarray, stamp_s: float) -> DepthScan:
    sensor = SensorParams()
    bearings = sensor.bearings_rad()
    ranges = cast_rays(np.array([pose.x_m, pose.y_m]), bearings + pose.yaw_rad, walls, sensor.max_range_m)
    return DepthScan(stamp_s, bearings, ranges, sensor.max_range_m)


def build_loop(walls: np.ndarray, drift: Pose2, path: list[Pose2]) -> LocalMap:
    """Keyframes along ``path`` (true poses), joined by odometry edges that are exact except the
    middle one, which carries ``drift``: the last keyframe revisits the first one's place."""
    m = LocalMap()
    prev: tuple[int, Pose2] | None = None
    for k, true in enumerate(path):
        polygon = scan_to_polygon(scan_at(true, walls, float(k)))
        rel = None if prev is None else path[k - 1].between(true)
        if rel is not None and k == len(path) // 2:
            rel = rel.compose(drift)
        parent = None if prev is None else (prev[0], rel)
        kf = m.add_keyframe(float(k), true, polygon, parent)
        prev = (kf.keyframe_id, true)
    return m


def search(m: LocalMap, keyframe_id: int, params: LoopClosingParams) -> list:
    matcher = ViewMatcher(params)
    matcher.start(keyframe_id)
    found = []
    for _ in range(50):
        if not matcher.busy:
            break
        closure = matcher.step(m)
        if closure is not None:
            found.append(closure)
    assert not matcher.busy
    return found


# Round the room: from the pillar's west side facing it, and back to the same place.
ROUND = [
    Pose2(3.0, 2.5, 0.0),
    *[Pose2(3.0 + 0.5 * k, 1.0, 0.0) for k in range(1, 5)],
    *[Pose2(7.0, 1.0 + 1.0 * k, math.pi / 2) for k in range(1, 4)],
    *[Pose2(7.0 - 1.0 * k, 4.8, math.pi) for k in range(1, 4)],
    Pose2(3.5, 3.5, -math.pi / 2),
    Pose2(3.1, 2.6, 0.05),
]


@pytest.mark.parametrize(
    "drift", [Pose2(0.0, 0.0, 0.0), Pose2(0.4, -0.3, 0.0), Pose2(0.0, 0.0, 0.08), Pose2(-0.3, 0.4, -0.05)]
)
def test_a_place_revisited_after_drift_is_joined_with_the_true_transform(drift):
    m = build_loop(ROOM, drift, ROUND)
    last = len(ROUND) - 1
    assert m.graph.reached(last).hops.max() >= 8
    found = search(m, last, LoopClosingParams(enabled=True))
    assert len(found) == 1
    closure = found[0]
    assert closure.later_id == last
    true = ROUND[closure.earlier_id].between(ROUND[last])
    err = true.between(closure.earlier_to_later)
    assert math.hypot(err.x_m, err.y_m) < 0.05 and abs(err.yaw_rad) < 0.02
    guessed = m.graph.relative(closure.earlier_id, last)
    off = true.between(guessed)
    assert math.hypot(off.x_m, off.y_m) > 0.3 or abs(off.yaw_rad) > 0.05 or drift == Pose2(0.0, 0.0, 0.0)


def test_no_loop_closure_is_made_from_too_far_a_jump_or_too_near_along_the_graph():
    m = build_loop(ROOM, Pose2(0.4, -0.3, 0.0), ROUND)
    last = len(ROUND) - 1
    # The match would move the view ~0.5 m: more than this allows for 12 hops of drift.
    assert search(m, last, LoopClosingParams(enabled=True, max_correction_m=0.1, max_correction_per_hop_m=0.01)) == []
    # Too few hops between the two views to look for one at all.
    assert search(m, last, LoopClosingParams(enabled=True, min_hops=len(ROUND))) == []


def test_the_explorer_joins_a_revisited_place_by_its_own_match_one_match_per_step(monkeypatch):
    """Fed scans round the room with odometry that jumps 0.4 m midway, the explorer takes
    keyframes, finds the revisit by matching, and joins it: one match at most per step, and
    the edge in a step after the one that found it (each costs milliseconds)."""

    calls: list[int] = []
    real = loop_closing.match_to_walls

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls[-1] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(loop_closing, "match_to_walls", counted)
    ex = Explorer(ExplorerParams(look_around_rad=0.0, loop_closing=LoopClosingParams(enabled=True)))
    drift = Pose2(0.4, -0.3, 0.0)
    # Round the room in 0.25 m steps between the waypoints, the odometry off by `drift` after halfway.
    poses: list[Pose2] = []
    for a, b in itertools.pairwise(ROUND):
        for t in np.linspace(0.0, 1.0, 5)[:-1]:
            yaw = a.yaw_rad + t * math.remainder(b.yaw_rad - a.yaw_rad, 2 * math.pi)
            poses.append(Pose2(a.x_m + t * (b.x_m - a.x_m), a.y_m + t * (b.y_m - a.y_m), yaw))
    poses += [ROUND[-1]] * 40  # then hover there while the matching runs
    closures_at: list[int] = []
    matched_at: list[int] = []
    for k, true in enumerate(poses):
        odom = true if k < len(poses) // 3 else Pose2.identity().compose(drift).compose(true)
        calls.append(0)
        before = ex.map.loop_closures
        had = ex._matched is not None
        ex.step(Odometry(0.1 * k, odom), scan_at(true, ROOM, 0.1 * k))
        if ex.map.loop_closures > before:
            closures_at.append(k)
            assert had  # found in an earlier step, joined in this one
        if ex._matched is not None:
            matched_at.append(k)
    assert max(calls) <= 1
    assert ex.loop_closures_matched >= 1 and ex.map.loop_closures == ex.loop_closures_matched
    assert all(c - 1 in matched_at for c in closures_at)
    for edge in ex.map.graph.edges:  # every edge it made is the true transform between the views
        if edge.kind is EdgeType.LOOP_CLOSURE:
            a, b = (round(ex.map.keyframes[i].stamp_s / 0.1) for i in (edge.from_id, edge.to_id))
            err = poses[a].between(poses[b]).between(edge.from_to)
            assert math.hypot(err.x_m, err.y_m) < 0.05 and abs(err.yaw_rad) < 0.02


@pytest.mark.parametrize(("elsewhere_at", "taken"), [(None, True), (2, False), (7, False)])
def test_a_match_that_a_restart_finds_elsewhere_as_well_is_not_taken(monkeypatch, elsewhere_at, taken):
    """The ambiguity test's logic, with the matching stubbed: every match lands on the same pose,
    except (when ``elsewhere_at`` is set) that call, which lands a metre along: then the views fit
    two places and no loop closure is made. Call 0 is the match, 1-4 the restarts shifted along
    and across the walls, 5-6 those turned, 7 the one from the graph's guess."""
    m = build_loop(ROOM, Pose2(0.4, -0.3, 0.0), ROUND)
    last = len(ROUND) - 1
    here = ROUND[0].between(ROUND[last])
    calls = []

    def aligned(points, walls, guess, params=None):  # type: ignore[no-untyped-def]
        calls.append(guess)
        pose = here if len(calls) - 1 != elsewhere_at else here.compose(Pose2(1.0, 0.0, 0.0))
        return pose, np.zeros(len(points)), np.tile([1.0, 0.0], (len(points), 1))

    def accepted(source, source_view, target, target_view, result, params=None):  # type: ignore[no-untyped-def]
        return ScanMatch(result[0], 30, 0.01, 0.4, (0.0, 1.0))

    monkeypatch.setattr(loop_closing, "match_to_walls", aligned)
    monkeypatch.setattr(loop_closing, "accept_match", accepted)
    params = LoopClosingParams(enabled=True, max_candidates=1)
    found = search(m, last, params)
    assert len(calls) == (8 if elsewhere_at is None else elsewhere_at + 1)  # it stops at the first disagreement
    assert (len(found) == 1) is taken
    if taken:
        assert found[0].earlier_to_later == here


def _stub_matching(monkeypatch, here: Pose2) -> list[Pose2]:
    """Every match lands on ``here`` and is accepted: the search's bookkeeping alone is tested."""
    calls: list[Pose2] = []

    def aligned(points, walls, guess, params=None):  # type: ignore[no-untyped-def]
        calls.append(guess)
        return here, np.zeros(len(points)), np.tile([1.0, 0.0], (len(points), 1))

    def accepted(source, source_view, target, target_view, result, params=None):  # type: ignore[no-untyped-def]
        return ScanMatch(result[0], 30, 0.01, 0.4, (0.0, 1.0))

    monkeypatch.setattr(loop_closing, "match_to_walls", aligned)
    monkeypatch.setattr(loop_closing, "accept_match", accepted)
    return calls


def test_a_new_keyframe_waits_for_a_match_under_its_ambiguity_test(monkeypatch):
    """A keyframe comes every few steps and a search spans several: a match found is tested to
    the end and joined, and only then is the newest keyframe searched for (the ones it replaced
    while waiting are not); a search with no match yet is dropped for the new keyframe."""
    m = build_loop(ROOM, Pose2(0.4, -0.3, 0.0), ROUND)
    last = len(ROUND) - 1
    here = ROUND[0].between(ROUND[last])
    calls = _stub_matching(monkeypatch, here)
    matcher = ViewMatcher(LoopClosingParams(enabled=True, max_candidates=1))
    matcher.start(last)
    assert matcher.step(m) is None  # its candidates
    assert matcher.step(m) is None and len(calls) == 1  # the match, now under test
    matcher.start(last - 2)
    matcher.start(last - 1)  # keyframes come meanwhile: the newest waits
    found = [c for c in (matcher.step(m) for _ in range(7)) if c is not None]
    assert [(c.earlier_id, c.later_id) for c in found] == [(0, last)] and len(calls) == 8
    assert matcher.busy  # then on to the newest keyframe, with a search of its own
    assert matcher.step(m) is None and len(calls) == 8  # its candidates: none faces its way
    assert matcher.step(m) is None and not matcher.busy
    # A search still looking for a match gives way to the new keyframe at once.
    matcher.start(last)
    assert matcher.step(m) is None  # candidates, no match yet
    matcher.start(last - 1)
    while matcher.busy:
        assert matcher.step(m) is None
    assert len(calls) == 8


def test_only_views_with_walls_near_the_new_views_points_are_candidates():
    """A match needs ``min_inliers`` points within its first gate of the old view's walls from
    its first iteration; candidates that cannot give that are passed over, not matched in vain
    (one step each), so the search reaches the views that can."""
    m = build_loop(ROOM, Pose2(0.4, -0.3, 0.0), ROUND)
    last = len(ROUND) - 1
    params = LoopClosingParams(enabled=True)
    source = loop_closing._view_points(m.keyframes[last], params.point_spacing_m)
    every = loop_closing.loop_closure_candidates(m, last, params)
    near = loop_closing.loop_closure_candidates(m, last, params, source)
    assert every and [c.old_id for c in near] == [c.old_id for c in every]  # the revisit shares walls
    for c in every:
        assert loop_closing.match_to_walls(source, m.keyframes[c.old_id].walls, c.guess, params.match) is not None
    # The same view's points 3 m off (past the 1 m gate of every wall) pair with none of them.
    far = source + np.array([3.0, 3.0])
    assert loop_closing.loop_closure_candidates(m, last, params, far) == []
    few = source[: params.match.min_inliers - 1]  # too few points to be matched at all
    assert loop_closing.loop_closure_candidates(m, last, params, few) == []


def test_a_guess_without_enough_pairs_is_one_the_match_gives_up_on():
    """``enough_pairs`` is the match's own first test, made beforehand: wherever it says no, the
    match from that guess fails, so passing such a candidate over loses no loop closure."""
    points = along(CORNER, 0.1)
    said_no = 0
    for dx, dy in itertools.product(np.linspace(-2.5, 2.5, 11), repeat=2):
        guess = Pose2(float(dx), float(dy), 0.1)
        if not enough_pairs(points, CORNER, guess):
            said_no += 1
            assert match_to_walls(points, CORNER, guess) is None
    assert 0 < said_no < 121  # near guesses pair, far ones do not
    assert enough_pairs(points, CORNER, Pose2.identity())
    assert not enough_pairs(points[:10], CORNER, Pose2.identity())  # fewer points than a match needs
