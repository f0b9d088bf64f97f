"""The open frontier set: which frontier vertices are still open and worth a flight."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.core.fov_polygon import KIND_FREE, KIND_FRONTIER, KIND_OBSTACLE
from companion.core.geometry import FloatArray, Pose2
from companion.core.local_map import Keyframe, LocalMap


@dataclass(frozen=True, slots=True)
class FrontierKey:
    """A frontier vertex: vertex ``index`` of keyframe ``keyframe_id``'s polygon."""

    keyframe_id: int
    index: int


@dataclass(frozen=True, slots=True)
class _RingRuns:
    """The runs of open vertices of a ring that has a closed vertex, walked from one so that no
    run wraps round: ``order[j]`` is the j-th vertex of that walk, and in walk order ``is_open``,
    ``first`` and ``last`` mark open vertices, runs' first and last ones, and ``run`` numbers the
    runs 1, 2, ... (0 for closed vertices)."""

    order: NDArray[np.intp]
    is_open: NDArray[np.bool_]
    first: NDArray[np.bool_]
    last: NDArray[np.bool_]
    run: NDArray[np.intp]

    @property
    def count(self) -> int:
        """The number of runs, plus one (run numbers index arrays of this size)."""
        return int(self.run.max()) + 1


def _ring_runs(is_open: NDArray[np.bool_]) -> _RingRuns:
    """The runs of ``is_open`` (some vertex must be closed)."""
    order = np.roll(np.arange(is_open.size), -int(np.flatnonzero(~is_open)[0]))
    run_open = is_open[order]
    first = run_open & ~np.roll(run_open, 1)
    last = run_open & ~np.roll(run_open, -1)
    run = np.where(run_open, np.cumsum(first), 0).astype(np.intp)
    return _RingRuns(order, run_open, first, last, run)


def run_sizes_m(kinds: NDArray[np.int8], vertices_xy: FloatArray) -> FloatArray:
    """For each open frontier vertex, the length of frontier its run of consecutive open frontier
    vertices spans (0 for other vertices). Tiny runs are fragments not worth a flight."""
    n = kinds.size
    is_open = kinds == KIND_FRONTIER
    sizes = np.zeros(n)
    if not is_open.any():
        return sizes
    edge_len = np.linalg.norm(np.roll(vertices_xy, -1, axis=0) - vertices_xy, axis=1)
    if is_open.all():
        sizes[:] = edge_len.sum()
        return sizes
    r = _ring_runs(is_open)
    run_len = edge_len[r.order]
    # Edges inside the run, and half of those into and out of it (they end at a vertex that is
    # not open): a lone open vertex between walls or seen space spans half of each.
    count = r.count
    inner = r.is_open & ~r.last
    inside = np.bincount(r.run[inner], run_len[inner], minlength=count)
    into = np.zeros(count)
    into[r.run[r.first]] = np.roll(run_len, 1)[r.first]
    out = np.zeros(count)
    out[r.run[r.last]] = run_len[r.last]
    # A lone open vertex between two closed as seen (other views saw the space on both sides of
    # it; the view's own origin, where the vehicle stood, counts as seen) spans nothing: two in
    # three flights to such vertices found nothing. Beside a wall (a gap seen through, or a vertex
    # closed as the wall it lies on) it spans half of each edge.
    kinds_o = kinds[r.order]
    seen_both = r.first & r.last & (np.roll(kinds_o, 1) == KIND_FREE) & (np.roll(kinds_o, -1) == KIND_FREE)
    into[r.run[seen_both]] = 0.0
    out[r.run[seen_both]] = 0.0
    total = 0.5 * (into + out) + inside
    sizes[r.order[r.is_open]] = total[r.run[r.is_open]]
    return sizes


def run_brackets(kinds: NDArray[np.int8]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """For each open frontier vertex, the vertex just before its run and the one just after it
    (-1 for other vertices, and when every vertex is open)."""
    is_open = kinds == KIND_FRONTIER
    before = np.full(kinds.size, -1, dtype=np.intp)
    after = np.full(kinds.size, -1, dtype=np.intp)
    if not is_open.any() or is_open.all():
        return before, after
    r = _ring_runs(is_open)
    b = np.zeros(r.count, dtype=np.intp)
    a = np.zeros(r.count, dtype=np.intp)
    b[r.run[r.first]] = np.roll(r.order, 1)[r.first]
    a[r.run[r.last]] = np.roll(r.order, -1)[r.last]
    before[r.order[r.is_open]] = b[r.run[r.is_open]]
    after[r.order[r.is_open]] = a[r.run[r.is_open]]
    return before, after


def walled_runs(kinds: NDArray[np.int8]) -> NDArray[np.bool_]:
    """For each open frontier vertex, whether its run lies between two obstacle vertices (a gap
    between walls: a door, or a corridor seen end-on), not beside space other views saw."""
    before, after = run_brackets(kinds)
    bracketed = (before >= 0) & (after >= 0)
    walled = bracketed & (kinds[before] == KIND_OBSTACLE) & (kinds[after] == KIND_OBSTACLE)
    return np.asarray(walled, dtype=bool)


def targetable_indices(kf: Keyframe, min_size_m: float) -> NDArray[np.intp]:
    """Open frontier vertices of a keyframe whose run is at least ``min_size_m`` long (memoised
    on the keyframe until a vertex closes: the planner asks for every keyframe it walks past)."""
    memo = kf.targetable_memo
    if memo is None or memo[0] != kf.version:
        memo = kf.targetable_memo = (kf.version, {})
    idx = memo[1].get(min_size_m)
    if idx is None:
        sizes = run_sizes_m(kf.kinds, kf.polygon.vertices_xy)
        idx = np.flatnonzero((kf.kinds == KIND_FRONTIER) & (sizes >= min_size_m))
        idx.flags.writeable = False  # shared by every caller until the next change
        memo[1][min_size_m] = idx
    return idx


@dataclass(frozen=True, slots=True)
class FrontierPoint:
    """An open frontier vertex expressed in some keyframe's frame, for reports and plots."""

    key: FrontierKey
    x_m: float
    y_m: float


def open_frontiers_in(local_map: LocalMap, frame_id: int, keyframe_ids: list[int] | None = None) -> list[FrontierPoint]:
    """Open frontier vertices of the given keyframes (all by default) in ``frame_id``'s frame."""
    ids = list(local_map.keyframes) if keyframe_ids is None else keyframe_ids
    out: list[FrontierPoint] = []
    for k in ids:
        kf = local_map.keyframes[k]
        idx = kf.open_frontier_indices()
        if idx.size == 0:
            continue
        pose: Pose2 = local_map.pose_in(frame_id, k)
        pts = pose.apply(kf.polygon.vertices_xy[idx])
        out.extend(
            FrontierPoint(FrontierKey(k, int(i)), float(x), float(y)) for i, (x, y) in zip(idx, pts, strict=True)
        )
    return out
