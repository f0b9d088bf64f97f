import math

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


def test_unknown_keyframes_and_bad_edges_raise():
    g = chain(2)
    with pytest.raises(GraphError):
        g.add_edge(0, 7, Pose2(), EdgeType.ODOMETRY)
    with pytest.raises(GraphError):
        g.add_edge(0, 1, Pose2(float("nan"), 0, 0), EdgeType.ODOMETRY)
    g.add_keyframe(9)
    with pytest.raises(GraphError):
        g.relative(0, 9)
