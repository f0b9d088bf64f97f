import math
import random
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from companion.core.errors import GraphError
from companion.core.geometry import Pose2
from companion.core.pose_graph import EdgeType, PoseGraph


def chain(n: int) -> PoseGraph:
    g = PoseGraph()
    for k in range(n):
        g.add_keyframe(k)
        if k:
            g.add_edge(k - 1, k, Pose2(1.0, 0.0, math.pi / 2), EdgeType.ODOMETRY)
    return g


def test_relative_composes_along_the_path():
    g = chain(5)
    rel = g.relative(0, 4)  # four quarter turns with 1 m steps: back at the start
    assert abs(rel.x_m) < 1e-9 and abs(rel.y_m) < 1e-9


def test_walk_is_breadth_first_and_loop_closure_shortens_hops():
    g = chain(6)
    assert [v.hops for v in g.walk(0)] == [0, 1, 2, 3, 4, 5]
    g.add_edge(0, 5, Pose2(0.0, -1.0, 0.0), EdgeType.LOOP_CLOSURE)
    hops = {v.keyframe_id: v.hops for v in g.walk(0)}
    assert hops[5] == 1 and g.path(0, 5) == [0, 5]


def test_walk_does_not_expand_rejected_branches():
    g = chain(5)
    visited = [v.keyframe_id for v in g.walk(0, accept=lambda k, _: k != 2)]
    assert visited == [0, 1]


def test_a_level_walk_bridges_a_few_refused_keyframes_in_a_row_and_returns_only_the_accepted():
    """Keyframes 2-4 (a turn in place looking away) are refused; with a bridge of three the walk
    goes on through them to 5 and 6, with their true hop counts; with two it stops at 4."""
    g = chain(8)

    def accept(ids: list[int], rows: np.ndarray) -> np.ndarray:
        return np.array([k not in (2, 3, 4) for k in ids], dtype=bool)

    bridged = {v.keyframe_id: v.hops for v in g.walk_levels(0, accept, bridge_hops=3)}
    assert bridged == {0: 0, 1: 1, 5: 5, 6: 6, 7: 7}
    assert [v.keyframe_id for v in g.walk_levels(0, accept, bridge_hops=2)] == [0, 1]
    assert [v.keyframe_id for v in g.walk_levels(0, accept)] == [0, 1]


def _random_graph(rng: random.Random, n: int) -> PoseGraph:
    """A chain of ``n`` keyframes with n / 4 loop closures between random pairs."""
    g = PoseGraph()
    for k in range(n):
        g.add_keyframe(k)
        if k:
            step = Pose2(rng.uniform(0.0, 1.0), rng.uniform(-0.3, 0.3), rng.uniform(-1.0, 1.0))
            g.add_edge(k - 1, k, step, EdgeType.ODOMETRY)
    for _ in range(n // 4):
        a, b = rng.sample(range(n), 2)
        g.add_edge(a, b, Pose2(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-3, 3)), EdgeType.LOOP_CLOSURE)
    return g


def _near_and_not(refused: set[int], calls: list[int]) -> Callable[[list[int], np.ndarray], np.ndarray]:
    """A level filter: keyframes within 4 m of the start and not ``refused``; counts its calls."""

    def accept(ids: list[int], rows: np.ndarray) -> np.ndarray:
        calls.append(len(ids))
        return np.array([k not in refused and math.hypot(x, y) < 4.0 for k, (x, y, _) in zip(ids, rows, strict=True)])

    return accept


def test_a_walk_asking_ahead_visits_the_same_keyframes_at_the_same_poses_in_fewer_calls():
    """Asking about keyframes beyond each level (``ahead``) is a speed setting: on random graphs
    (a chain with loop closures, some of them shortcuts past refused keyframes) the walk returns
    the same visits, hops and poses to the bit as asking level by level, in fewer calls."""
    rng = random.Random(7)
    for trial in range(30):
        n = rng.randrange(5, 60)
        g = _random_graph(rng, n)
        refused = set(rng.sample(range(n), n // 5))
        start, bridge = rng.randrange(n), trial % 4
        plain_calls: list[int] = []
        ahead_calls: list[int] = []
        plain = g.walk_levels(start, _near_and_not(refused, plain_calls), bridge, 0.2)
        ahead = g.walk_levels(start, _near_and_not(refused, ahead_calls), bridge, 0.2, ahead=16)
        assert [(v.keyframe_id, v.hops, v.pose_in_start) for v in ahead] == [
            (v.keyframe_id, v.hops, v.pose_in_start) for v in plain
        ]
        assert len(ahead_calls) <= len(plain_calls)
    # Along a chain every level holds one keyframe: 39 calls, or three (each the level's one
    # and 16 beyond), every keyframe asked once (1 m steps turning a quarter: all within 4 m).
    counted: list[int] = []
    everything = chain(40).walk_levels(0, _near_and_not(set(), counted), ahead=16)
    assert len(everything) == 40
    assert counted == [17, 17, 5]


def test_unknown_keyframes_and_bad_edges_raise():
    g = chain(2)
    with pytest.raises(GraphError):
        g.add_edge(0, 7, Pose2(), EdgeType.ODOMETRY)
    with pytest.raises(GraphError):
        g.add_edge(0, 1, Pose2(float("nan"), 0, 0), EdgeType.ODOMETRY)
    g.add_keyframe(9)
    with pytest.raises(GraphError):
        g.relative(0, 9)


def _as_walk(g: PoseGraph, start: int) -> dict[int, tuple[int, tuple[float, float, float]]]:
    return {
        v.keyframe_id: (v.hops, (v.pose_in_start.x_m, v.pose_in_start.y_m, v.pose_in_start.yaw_rad))
        for v in g.walk(start)
    }


def _as_reached(
    g: PoseGraph, start: int, max_hops: int | None = None
) -> dict[int, tuple[int, tuple[float, float, float]]]:
    r = g.reached(start, max_hops)
    return {int(k): (int(h), tuple(float(c) for c in p)) for k, h, p in zip(r.ids, r.hops, r.poses, strict=True)}


def test_reached_matches_the_walk_as_the_graph_grows_and_closes_loops():
    """Kept per start and extended by new leaves, it must still say what a fresh walk says; a
    loop closure (which shortens paths) and a keyframe joining two others must not be missed."""
    g = PoseGraph()
    step = Pose2(1.0, 0.1, 0.2)
    g.add_keyframe(0)
    for k in range(1, 8):
        g.add_keyframe(k)
        g.add_edge(k - 1, k, step, EdgeType.ODOMETRY)
        for start in (0, k // 2):
            assert _as_reached(g, start) == _as_walk(g, start)
    g.add_edge(1, 7, Pose2(0.5, -2.0, 1.0), EdgeType.LOOP_CLOSURE)
    assert _as_reached(g, 0)[7][0] == 2 and _as_reached(g, 0) == _as_walk(g, 0)
    g.add_keyframe(8)  # hangs off 7 by odometry, then 2 closes a loop onto it
    g.add_edge(7, 8, step, EdgeType.ODOMETRY)
    assert _as_reached(g, 3) == _as_walk(g, 3)
    g.add_edge(2, 8, Pose2(-1.0, 1.0, 0.5), EdgeType.LOOP_CLOSURE)
    assert _as_reached(g, 3)[8][0] == 2 and _as_reached(g, 3) == _as_walk(g, 3)
    g.add_keyframe(9)
    g.add_keyframe(10)
    g.add_edge(9, 10, step, EdgeType.ODOMETRY)  # a separate piece (after a reset) ...
    assert 9 not in _as_reached(g, 0)
    g.add_edge(8, 9, step, EdgeType.ODOMETRY)  # ... joined later, bringing 10 along
    assert _as_reached(g, 0) == _as_walk(g, 0) and 10 in _as_reached(g, 0)


def _growing_graphs(seed: int) -> Iterator[tuple[PoseGraph, list[int], random.Random]]:
    """Sixty random pose graphs grown one change at a time (a leaf, a branch, a loop closure),
    each yielded after every change with a few keyframes to walk from (and the generator, for
    the caller's own draws)."""
    rng = random.Random(seed)
    for _ in range(60):
        g = PoseGraph()
        g.add_keyframe(0)
        n = 1
        for _ in range(50):
            rel = Pose2(rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-3, 3))
            if rng.random() < 0.7 or n < 3:
                g.add_keyframe(n)
                g.add_edge(rng.randrange(n) if rng.random() < 0.2 else n - 1, n, rel, EdgeType.ODOMETRY)
                n += 1
            else:
                a, b = rng.sample(range(n), 2)
                g.add_edge(a, b, rel, EdgeType.LOOP_CLOSURE)
            yield g, rng.sample(range(n), min(3, n)), rng


def test_reached_stays_the_walk_as_the_graph_grows_and_closes_loops():
    """``reached`` is kept per start and extended by new leaves rather than walked again; whatever
    the graph does (leaves, branches, loop closures), it must answer as a fresh walk does, to the
    bit."""
    for g, starts, _ in _growing_graphs(3):
        for start in starts:
            assert _as_reached(g, start) == _as_walk(g, start)


def test_reached_to_a_depth_holds_every_keyframe_that_near_as_a_whole_walk_does():
    """A walk asked to go only ``max_hops`` deep (kept, extended, or walked afresh) must hold
    every keyframe within that many hops, with the whole walk's hops and pose to the bit, and
    nothing the whole walk does not say; asked deeper than it went, it walks again."""
    for g, starts, rng in _growing_graphs(5):
        for start in starts:
            depth = rng.choice([None, 1, 2, 4, 8])
            mine, walk = _as_reached(g, start, depth), _as_walk(g, start)
            within = {k: v for k, v in walk.items() if depth is None or v[0] <= depth}
            assert {k: v for k, v in mine.items() if k in within} == within
            assert all(walk[k] == v for k, v in mine.items())


def test_reached_arrays_are_shared_read_only_until_the_walk_grows():
    """Every caller gets the same cached arrays, so none may write to them; a new leaf gives new
    arrays with it."""
    g = PoseGraph()
    for k in range(3):
        g.add_keyframe(k)
    g.add_edge(0, 1, Pose2(1.0, 0.0, 0.0), EdgeType.ODOMETRY)
    g.add_edge(1, 2, Pose2(1.0, 0.0, 0.5), EdgeType.ODOMETRY)
    first = g.reached(0)
    assert g.reached(0) is first
    with pytest.raises(ValueError):
        first.poses[0, 0] = 9.0
    g.add_keyframe(3)
    g.add_edge(2, 3, Pose2(1.0, 0.0, 0.0), EdgeType.ODOMETRY)
    grown = g.reached(0)
    assert grown is not first and 3 in grown.ids.tolist() and 3 not in first.ids.tolist()


def test_a_keyframe_as_many_hops_either_way_is_placed_through_the_loop_closure():
    """Keyframe 2 is two hops from 4 along odometry (4-3-2) and two through a loop closure
    (4-1-2). Odometry carries every metre's drift; a loop closure is measured. The walk, paths
    and poses go through the loop closure."""
    g = PoseGraph()
    for k in range(5):
        g.add_keyframe(k)
    truth = [Pose2(float(k), 0.0, 0.0) for k in range(5)]
    drift = Pose2(0.0, 0.1, 0.02)  # each odometry edge a little off
    for k in range(1, 5):
        g.add_edge(k - 1, k, truth[k - 1].between(truth[k]).compose(drift), EdgeType.ODOMETRY)
    g.add_edge(1, 4, truth[1].between(truth[4]), EdgeType.LOOP_CLOSURE)
    via_closure = truth[4].between(truth[1]).compose(g.relative(1, 2))
    walked = {v.keyframe_id: v.pose_in_start for v in g.walk(4)}
    assert g.path(4, 2) == [4, 1, 2]
    for pose in (walked[2], g.relative(4, 2)):
        assert math.isclose(pose.x_m, via_closure.x_m, abs_tol=1e-12)
        assert math.isclose(pose.y_m, via_closure.y_m, abs_tol=1e-12)
    reached = g.reached(4)
    row = int(list(reached.ids).index(2))
    assert math.isclose(float(reached.poses[row, 1]), via_closure.y_m, abs_tol=1e-12)
