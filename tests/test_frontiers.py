"""Frontier runs: which open frontier vertices are worth a flight."""

import math

import numpy as np
import pytest

from companion.core.fov_polygon import PolygonParams, VertexKind, scan_to_polygon
from companion.core.frontiers import run_brackets, run_sizes_m, targetable_indices, walled_runs
from companion.core.geometry import Pose2
from companion.core.local_map import Keyframe
from companion.core.messages import DepthScan

F, W, FREE = VertexKind.FRONTIER, VertexKind.OBSTACLE, VertexKind.FREE  # W: a wall (obstacle)


def ring(n: int, spacing_m: float = 0.25) -> np.ndarray:
    """n vertices along a line ``spacing_m`` apart, closed back to the first (a long last edge)."""
    return np.column_stack((np.arange(n) * spacing_m, np.zeros(n)))


def test_a_lone_open_vertex_spans_half_of_each_edge_beside_it():
    """A single open vertex between a wall and seen space is a fragment about one vertex wide,
    not the two full edges beside it (it would otherwise be worth a flight)."""
    kinds = np.array([W, W, F, FREE, FREE, W], dtype=np.int8)
    sizes = run_sizes_m(kinds, ring(6))
    assert sizes[2] == pytest.approx(0.25)
    assert np.all(sizes[kinds != F] == 0.0)


def test_a_lone_open_vertex_left_between_seen_spans_nothing():
    """Its neighbours closed by views that saw beyond them, a lone open vertex spans no
    frontier: not worth a flight (two in three flights to such vertices found nothing). Two
    open vertices there still span the edge between them."""
    kinds = np.array([W, FREE, F, FREE, W, W], dtype=np.int8)
    assert run_sizes_m(kinds, ring(6))[2] == 0.0
    pair = np.array([W, FREE, F, F, FREE, W], dtype=np.int8)
    assert np.allclose(run_sizes_m(pair, ring(6))[2:4], 0.125 + 0.25 + 0.125)


def test_a_run_spans_its_inner_edges_and_half_of_its_end_edges():
    kinds = np.array([W, F, F, F, W, W], dtype=np.int8)
    sizes = run_sizes_m(kinds, ring(6))
    assert np.allclose(sizes[1:4], 0.125 + 0.5 + 0.125)


def test_an_all_open_ring_spans_its_perimeter():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    sizes = run_sizes_m(np.full(4, F, dtype=np.int8), square)
    assert np.allclose(sizes, 4.0)


def test_a_run_between_two_walls_is_walled_one_beside_seen_space_is_not():
    """A gap between walls (a corridor seen end-on, a door) may be the way on however short its
    run; a run beside space other views saw is a remnant of what they saw. The ring wraps: the
    run at its end lies between the last wall and the first."""
    kinds = np.array([F, W, F, F, W, FREE, F, W, W, F], dtype=np.int8)
    walled = walled_runs(kinds)
    assert walled.tolist() == [True, False, True, True, False, False, False, False, False, True]
    assert not walled_runs(np.full(4, F, dtype=np.int8)).any()  # no wall at all: nothing brackets it
    assert not walled_runs(np.full(4, W, dtype=np.int8)).any()


def test_each_open_vertex_knows_the_vertices_just_before_and_after_its_run():
    kinds = np.array([F, W, F, F, W, FREE, F, W, W, F], dtype=np.int8)
    before, after = run_brackets(kinds)
    assert before.tolist() == [8, -1, 1, 1, -1, -1, 5, -1, -1, 8]
    assert after.tolist() == [1, -1, 4, 4, -1, -1, 7, -1, -1, 1]
    assert (run_brackets(np.full(3, F, dtype=np.int8))[0] == -1).all()


def test_the_targetable_vertices_at_each_size_are_remembered_until_a_vertex_closes():
    """A route search asks every keyframe at two sizes in turn: each size's answer is kept, the
    same as one computed afresh, until a vertex closes; then each is computed again."""
    scan = DepthScan(0.0, np.linspace(-math.pi / 4, math.pi / 4, 64), np.full(64, 5.0), 5.0)
    kf = Keyframe(0, 0.0, Pose2(), scan_to_polygon(scan, PolygonParams(side_frontier_spacing_m=0.0)))

    def fresh(size_m: float) -> np.ndarray:
        sizes = run_sizes_m(kf.kinds, kf.polygon.vertices_xy)
        return np.flatnonzero((kf.kinds == VertexKind.FRONTIER) & (sizes >= size_m))

    for size_m in (0.6, 0.3, 0.6, 0.3, 4.0):
        assert np.array_equal(targetable_indices(kf, size_m), fresh(size_m))
    assert targetable_indices(kf, 0.6) is targetable_indices(kf, 0.6)  # remembered, not recomputed
    open_now = targetable_indices(kf, 0.3)
    kf.close(open_now[: open_now.size // 2])
    for size_m in (0.6, 0.3):
        assert np.array_equal(targetable_indices(kf, size_m), fresh(size_m))
    assert targetable_indices(kf, 0.3).size < open_now.size
