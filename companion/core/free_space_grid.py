"""Paths through a view's known free space, for goals a straight line does not reach.

Rapid frontier selection (thesis 2.9) flies straight lines. A frontier seen through a door at an
angle, or a keyframe behind a door jamb, has no clear straight path from where the vehicle is, yet
the known free space joins them. This module rasterises a view's known free space (its grown
polygon, eroded by the clearance, with every obstacle edge the view holds and the live scan's
returns blocked too), runs a breadth-first wavefront from the vehicle, and returns a few waypoints
along the shortest grid path, shortened by line of sight.

numpy only for the search (a vectorised wavefront, no per-cell Python loop); shapely to rasterise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.geometry import FloatArray

_UNREACHED = -1


@dataclass(frozen=True, slots=True)
class GridParams:
    """Resolution of the free-space grid and how far from walls and unknown space its cells keep."""

    cell_m: float = 0.15
    snap_m: float = 0.4  # a start (or a goal that allows it) in a blocked cell moves to a free cell this close
    centring_cells: int = 3  # a path's corners move up to this many cells away from walls


def disk_offsets(radius_cells: float) -> list[tuple[int, int]]:
    r = math.floor(radius_cells)
    return [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dy * dy + dx * dx <= radius_cells**2]


def _dilate(mask: NDArray[np.bool_], offsets: list[tuple[int, int]]) -> NDArray[np.bool_]:
    """Every cell within the offsets of a set cell (binary dilation by shifting)."""
    out = mask.copy()
    ny, nx = mask.shape
    for dy, dx in offsets:
        if dy == 0 and dx == 0:
            continue
        ys, yd = (slice(0, ny - dy), slice(dy, ny)) if dy >= 0 else (slice(-dy, ny), slice(0, ny + dy))
        xs, xd = (slice(0, nx - dx), slice(dx, nx)) if dx >= 0 else (slice(-dx, nx), slice(0, nx + dx))
        out[yd, xd] |= mask[ys, xs]
    return out


def _dilate_square(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """:func:`_dilate` by the 8 neighbours, as two passes of 3 cells (rows, then columns):
    the same cells in half the array operations (the wavefront runs it once per step)."""
    rows = mask.copy()
    rows[:, 1:] |= mask[:, :-1]
    rows[:, :-1] |= mask[:, 1:]
    out = rows.copy()
    out[1:, :] |= rows[:-1, :]
    out[:-1, :] |= rows[1:, :]
    return out


_NEIGHBOURS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
_CROSS = [(-1, 0), (0, -1), (0, 1), (1, 0)]


@dataclass(frozen=True, slots=True)
class FreeSpaceGrid:
    """Cells whose centre keeps the clearance from walls and unknown space; row = y, column = x."""

    origin_xy: tuple[float, float]  # centre of cell (0, 0)
    cell_m: float
    clearance_m: float
    blocked: NDArray[np.bool_]  # not known free, or an obstacle sample (before erosion)
    free: NDArray[np.bool_]  # far enough from every blocked cell
    params: GridParams
    depth: NDArray[np.int8]  # how many cells deeper than the clearance a free cell lies (0 at the edge)

    @staticmethod
    def build(
        free_space: shapely.Geometry | NDArray[np.object_],
        obstacle_segments: FloatArray,
        clearance_m: float,
        params: GridParams | None = None,
    ) -> FreeSpaceGrid:
        """Rasterise ``free_space`` (a polygon, or an array of polygons whose union it is, in some
        frame) with the obstacle segments (M, 2, 2) blocked, then erode by ``clearance_m`` (less
        half a cell, so a door exactly twice the clearance plus a cell wide stays open).
        Polygons are rasterised over their own bounding boxes (:meth:`_inside_any`): the same
        cells as their union gives, without building it (a union of 50 views takes 15-20 ms)."""
        p = params or GridParams()
        cell = p.cell_m
        shapes = np.atleast_1d(np.asarray(free_space, dtype=object))
        shapes = shapes[~shapely.is_empty(shapes)] if shapes.size else shapes
        # Bounds on the millimetre grid the union snaps to: the same cells as a grid of the union.
        minx, miny, maxx, maxy = np.round(shapely.total_bounds(shapes), 3) if shapes.size else (0.0, 0.0, 0.0, 0.0)
        pad = clearance_m + 2 * cell
        x0, y0 = minx - pad, miny - pad
        nx = max(1, math.ceil((maxx + pad - x0) / cell))
        ny = max(1, math.ceil((maxy + pad - y0) / cell))
        empty = np.zeros((ny, nx), dtype=bool)
        grid = FreeSpaceGrid((x0, y0), cell, clearance_m, empty, empty, p, empty.astype(np.int8))
        inside = grid._inside_any(shapes)
        # A cell whose centre falls in a sliver between two views' near-coincident edges is no
        # unknown space: open it when the cells on both sides of it (left and right, or above and
        # below) are inside (the union's snap rounding closed such slivers; a line of blocked
        # cells, eroded, closes a door).
        sliver = np.zeros_like(inside)
        sliver[:, 1:-1] |= inside[:, :-2] & inside[:, 2:]
        sliver[1:-1, :] |= inside[:-2, :] & inside[2:, :]
        blocked = ~(inside | sliver)
        grid._mark(blocked, sample_segments(obstacle_segments, cell / 2.0))
        return grid._eroded(blocked)

    def with_blocked_points(self, points_xy: FloatArray) -> FreeSpaceGrid:
        """A copy with cells at the points blocked too (e.g. the newest scan's returns)."""
        if points_xy.shape[0] == 0:
            return self
        blocked = self.blocked.copy()
        self._mark(blocked, points_xy)
        return self._eroded(blocked)

    def with_live_scan(self, returns_xy: FloatArray, live_view: shapely.Geometry | None) -> FreeSpaceGrid:
        """A copy that trusts the newest scan where it sees: cells inside its free-space polygon
        are open even where an older (drifted) view put a wall or unknown space, and its returns
        are blocked."""
        if live_view is None or live_view.is_empty:
            return self.with_blocked_points(returns_xy)
        i0, i1, j0, j1 = self._window(live_view.bounds)
        blocked = self.blocked.copy()
        if i0 < i1 and j0 < j1:
            blocked[i0:i1, j0:j1] &= ~self._inside(live_view, i0, i1, j0, j1)
        self._mark(blocked, returns_xy)
        return self._eroded(blocked)

    def is_free(self, points_xy: FloatArray) -> NDArray[np.bool_]:
        ij = self._cells(points_xy)
        ok = self._in_grid(ij)
        out = np.zeros(points_xy.shape[0], dtype=bool)
        out[ok] = self.free[ij[ok, 0], ij[ok, 1]]
        return out

    def line_free(self, a_xy: FloatArray, b_xy: FloatArray) -> bool:
        """Every cell along the segment a-b is free."""
        n = max(2, math.ceil(float(np.hypot(*(b_xy - a_xy))) / (self.cell_m / 2.0)) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        return bool(self.is_free(a_xy + t * (b_xy - a_xy)).all())

    def lines_free(self, a_xy: FloatArray, ends_xy: FloatArray) -> NDArray[np.bool_]:
        """:meth:`line_free` from ``a_xy`` to each of the ends (K, 2), in one pass: the same
        points along each segment, to the bit."""
        ends = np.asarray(ends_xy, dtype=np.float64).reshape(-1, 2)
        if ends.shape[0] == 0:
            return np.zeros(0, dtype=bool)
        d = ends - a_xy
        div = np.maximum(1, np.ceil(np.hypot(d[:, 0], d[:, 1]) / (self.cell_m / 2.0)).astype(np.intp))
        seg = np.repeat(np.arange(ends.shape[0]), div + 1)
        first = np.cumsum(div + 1) - (div + 1)
        t = (np.arange(seg.size) - first[seg]) * (1.0 / div)[seg]  # np.linspace's points
        t[first + div] = 1.0
        free = self.is_free(a_xy + t[:, None] * d[seg])
        blocked = np.bincount(seg, ~free, minlength=ends.shape[0])
        out: NDArray[np.bool_] = blocked == 0
        return out

    def reach_from(self, start_xy: FloatArray) -> Reach | None:
        """The wavefront from the free cell at (or nearest to) ``start_xy``; None when there is none."""
        start = self._snap(start_xy)
        if start is None:
            return None
        dist = np.full(self.free.shape, _UNREACHED, dtype=np.int32)
        dist[start] = 0
        front = np.zeros(self.free.shape, dtype=bool)
        front[start] = True
        visited = front.copy()
        step = 0
        while front.any():
            step += 1
            nxt = _dilate_square(front) & self.free & ~visited
            dist[nxt] = step
            visited |= nxt
            front = nxt
        return Reach(self, np.asarray(start_xy, dtype=np.float64), dist)

    def cell_centre(self, i: int, j: int) -> FloatArray:
        return np.array([self.origin_xy[0] + j * self.cell_m, self.origin_xy[1] + i * self.cell_m])

    def _in_grid(self, ij: NDArray[np.intp]) -> NDArray[np.bool_]:
        ny, nx = self.blocked.shape
        inside: NDArray[np.bool_] = (ij[:, 0] >= 0) & (ij[:, 0] < ny) & (ij[:, 1] >= 0) & (ij[:, 1] < nx)
        return inside

    def _window(self, bounds: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
        """Rows i0:i1 and columns j0:j1 (clipped to the grid) whose cell centres can lie inside
        a shape with these bounds (minx, miny, maxx, maxy)."""
        minx, miny, maxx, maxy = bounds
        ny, nx = self.blocked.shape
        j0 = max(0, int((minx - self.origin_xy[0]) / self.cell_m))
        j1 = min(nx, int((maxx - self.origin_xy[0]) / self.cell_m) + 2)
        i0 = max(0, int((miny - self.origin_xy[1]) / self.cell_m))
        i1 = min(ny, int((maxy - self.origin_xy[1]) / self.cell_m) + 2)
        return i0, i1, j0, j1

    def _inside_any(self, shapes: NDArray[np.object_]) -> NDArray[np.bool_]:
        """Which cells have their centre inside any of the shapes. Each shape tests the cells of
        its bounding box that no earlier batch of shapes set; the shapes go in batches of 1, 2,
        3, ... shapes, each batch in one ``contains_xy`` call: the first views set most cells,
        and a call per view (100 of them, most testing a few cells) cost more than its tests."""
        inside = np.zeros(self.blocked.shape, dtype=bool)
        if shapes.size == 0:
            return inside
        ny, nx = self.blocked.shape
        x0, y0 = self.origin_xy
        b = shapely.bounds(shapes)  # the same windows as _window, for all shapes at once
        j0 = np.maximum(0, ((b[:, 0] - x0) / self.cell_m).astype(np.intp))
        j1 = np.minimum(nx, ((b[:, 2] - x0) / self.cell_m).astype(np.intp) + 2)
        i0 = np.maximum(0, ((b[:, 1] - y0) / self.cell_m).astype(np.intp))
        i1 = np.minimum(ny, ((b[:, 3] - y0) / self.cell_m).astype(np.intp) + 2)
        shapely.prepare(shapes)  # else each point's test prepares its shape again
        xs = x0 + self.cell_m * np.arange(nx)
        ys = y0 + self.cell_m * np.arange(ny)
        start, size = 0, 1
        while start < shapes.size:
            batch = range(start, min(shapes.size, start + size))
            start, size = start + size, size + 1
            cells = [np.nonzero(~inside[i0[k] : i1[k], j0[k] : j1[k]]) for k in batch]
            counts = [rc[0].size for rc in cells]
            owner = np.repeat(np.asarray(batch), counts)
            if owner.size:
                r = np.concatenate([rc[0] for rc in cells]) + i0[owner]
                c = np.concatenate([rc[1] for rc in cells]) + j0[owner]
                hit = shapely.contains_xy(shapes[owner], xs[c], ys[r])
                inside[r[hit], c[hit]] = True
        return inside

    def _inside(self, shape: shapely.Geometry, i0: int, i1: int, j0: int, j1: int) -> NDArray[np.bool_]:
        """Which cells of rows i0:i1, columns j0:j1 have their centre inside ``shape``."""
        out = np.zeros((i1 - i0, j1 - j0), dtype=bool)
        rows, cols = np.nonzero(~out)
        if rows.size:
            x = self.origin_xy[0] + self.cell_m * (j0 + cols)
            y = self.origin_xy[1] + self.cell_m * (i0 + rows)
            hit = shapely.contains_xy(shape, x, y)
            out[rows[hit], cols[hit]] = True
        return out

    def _mark(self, blocked: NDArray[np.bool_], points_xy: FloatArray) -> None:
        """Block (in place) the cells the points fall in."""
        if points_xy.shape[0]:
            ij = self._cells(points_xy)
            ij = ij[self._in_grid(ij)]
            blocked[ij[:, 0], ij[:, 1]] = True

    def _eroded(self, blocked: NDArray[np.bool_]) -> FreeSpaceGrid:
        """The grid for these blocked cells: free where no blocked cell is within the clearance,
        and how many cells deeper than that each free cell lies."""
        radius_cells = max(0.0, (self.clearance_m - self.cell_m / 2.0) / self.cell_m)
        not_free = _dilate(blocked, disk_offsets(radius_cells))
        depth = np.zeros(blocked.shape, dtype=np.int8)
        deeper = not_free
        for _ in range(self.params.centring_cells):
            deeper = _dilate(deeper, _CROSS)
            depth += ~deeper
        return replace(self, blocked=blocked, free=~not_free, depth=depth)

    def _cells(self, points_xy: FloatArray) -> NDArray[np.intp]:
        pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
        j = np.rint((pts[:, 0] - self.origin_xy[0]) / self.cell_m).astype(np.intp)
        i = np.rint((pts[:, 1] - self.origin_xy[1]) / self.cell_m).astype(np.intp)
        return np.column_stack((i, j))

    def _snap(self, xy: FloatArray, mask: NDArray[np.bool_] | None = None) -> tuple[int, int] | None:
        """The free (and, if given, masked) cell nearest ``xy`` within ``snap_m``."""
        allowed = self.free if mask is None else self.free & mask
        i, j = (int(v) for v in self._cells(np.asarray(xy))[0])
        r = math.ceil(self.params.snap_m / self.cell_m)
        ny, nx = allowed.shape
        i0, i1, j0, j1 = max(0, i - r), min(ny, i + r + 1), max(0, j - r), min(nx, j + r + 1)
        if i0 >= i1 or j0 >= j1:
            return None
        window = allowed[i0:i1, j0:j1]
        if not window.any():
            return None
        wi, wj = np.nonzero(window)
        d2 = (wi + i0 - i) ** 2 + (wj + j0 - j) ** 2
        k = int(np.argmin(d2))
        if d2[k] * self.cell_m**2 > self.params.snap_m**2:
            return None
        return int(wi[k] + i0), int(wj[k] + j0)


@dataclass(frozen=True, slots=True)
class Reach:
    """Grid steps from a start cell to every free cell connected to it."""

    grid: FreeSpaceGrid
    start_xy: FloatArray
    steps: NDArray[np.int32]

    def path_to(self, goal_xy: FloatArray, snap: bool = False) -> FloatArray | None:
        """Waypoints (K, 2) from the start to ``goal_xy``, the goal last, shortened by line of
        sight over free cells; None when the goal is not connected to the start. A goal closer to
        a wall than the clearance is not reached, unless ``snap``: then the path ends at the
        nearest free cell within ``snap_m`` instead (e.g. a keyframe taken close to a wall)."""
        g = self.grid
        ny, nx = self.steps.shape
        gi, gj = (int(v) for v in g._cells(np.asarray(goal_xy))[0])
        if snap:
            goal_cell = g._snap(goal_xy, self.steps != _UNREACHED)
        else:
            # One cell to look at: the whole grid's reached mask cost more than the rest of a
            # failed call, and a step may ask for a few hundred goals.
            inside = 0 <= gi < ny and 0 <= gj < nx
            goal_cell = (gi, gj) if inside and self.steps[gi, gj] != _UNREACHED else None
        if goal_cell is None:
            return None
        cells = [goal_cell]
        i, j = goal_cell
        while self.steps[i, j] > 0:
            here = self.steps[i, j]
            best: tuple[int, int] | None = None
            for di, dj in _NEIGHBOURS:
                a, b = i + di, j + dj
                if 0 <= a < ny and 0 <= b < nx and self.steps[a, b] == here - 1:
                    best = (a, b)
                    break
            assert best is not None  # a reached cell always has a downhill neighbour
            i, j = best
            cells.append(best)
        cells.reverse()
        pts = [g.cell_centre(a, b) for a, b in cells]
        if cells[-1] == (gi, gj):
            pts[-1] = np.asarray(goal_xy, dtype=np.float64)
        return self._centre(self._shorten(pts))

    def nearest_to(self, targets_xy: FloatArray) -> FloatArray | None:
        """For each target (N, 2), the centre of the reached cell nearest it (None when nothing
        is reached): as close to places out of reach as the free space leads."""
        cells = np.argwhere(self.steps != _UNREACHED)
        if cells.shape[0] == 0:
            return None
        centres = self.grid.origin_xy + cells[:, ::-1] * self.grid.cell_m
        t = np.asarray(targets_xy, dtype=np.float64).reshape(-1, 2)
        d = np.hypot(centres[None, :, 0] - t[:, None, 0], centres[None, :, 1] - t[:, None, 1])
        return np.asarray(centres[np.argmin(d, axis=1)], dtype=np.float64)

    def _shorten(self, pts: list[FloatArray]) -> FloatArray:
        """Greedy line of sight: from where the path stands, jump to the farthest point it sees."""
        out: list[FloatArray] = []
        cur, k = self.start_xy, 0
        ahead = np.vstack(pts)
        while k < len(pts) - 1:
            seen = np.flatnonzero(self.grid.lines_free(cur, ahead[k + 1 :]))
            far = k + 1 + int(seen[-1]) if seen.size else k + 1
            out.append(pts[far])
            cur, k = pts[far], far
        if not out:
            out.append(pts[-1])
        return np.vstack(out)

    def _centre(self, path: FloatArray) -> FloatArray:
        """Move each corner (every waypoint but the goal) to the deepest free cell near it, where
        the legs on both sides stay free: a shortest path hugs door jambs; a flown one should not."""
        g = self.grid
        r = g.params.centring_cells
        ny, nx = g.depth.shape
        out = path.copy()
        for k in range(path.shape[0] - 1):
            i, j = (int(v) for v in g._cells(out[k])[0])
            i0, i1, j0, j1 = max(0, i - r), min(ny, i + r + 1), max(0, j - r), min(nx, j + r + 1)
            window = np.where(g.free[i0:i1, j0:j1], g.depth[i0:i1, j0:j1], -1).astype(np.int32)
            wi, wj = np.nonzero(window >= 0)
            if wi.size == 0:
                continue
            d2 = (wi + i0 - i) ** 2 + (wj + j0 - j) ** 2
            order = np.lexsort((d2, -window[wi, wj]))  # deepest first, then nearest
            before = self.start_xy if k == 0 else out[k - 1]
            for m in order[:8]:
                cand = g.cell_centre(int(wi[m] + i0), int(wj[m] + j0))
                if (g.line_free(before, cand) or k == 0) and g.line_free(cand, out[k + 1]):
                    out[k] = cand
                    break
        return out


def sample_segments(segments: FloatArray, spacing_m: float) -> FloatArray:
    """Points along each segment (M, 2, 2), no farther apart than ``spacing_m``."""
    if segments.shape[0] == 0:
        return np.zeros((0, 2))
    a, b = segments[:, 0, :], segments[:, 1, :]
    n = np.maximum(1, np.ceil(np.hypot(*(b - a).T) / spacing_m).astype(np.intp))
    reps = n + 1
    seg = np.repeat(np.arange(segments.shape[0]), reps)
    # np.linspace(0, 1, n + 1) for every segment at once, to the bit: i * (1 / n), the last 1.
    first = np.cumsum(reps) - reps
    t = (np.arange(seg.size) - first[seg]) * (1.0 / n)[seg]
    t[first + n] = 1.0
    points: FloatArray = a[seg] + t[:, None] * (b[seg] - a[seg])
    return points
