"""Frontier vertices whose unseen space is only a sliver: nothing there is worth a flight.

A view that looks past a wall's end, or along a wall at a grazing angle, leaves frontier vertices
whose unseen space is a thin strip between the free space other views saw and a wall, or a pocket
behind the gap two views left between a wall's faces at a corner. Eq. 2.15 cannot close them (no
view holds the space beyond them: it is unseen), and flying back to one learns a few square
decimetres. The grid baseline never goes for such space (its frontier cells must keep its
clearance from walls); the polygon planner flew back along a spiral for them after coverage was
full (spiral seed 1: coverage 1.000 at 192 s, `complete` at 284 s).

The test rasterises a window round each vertex: cells inside any view are seen, cells a wall
crosses are walls. The vertex's frontier is worth a flight when a disk of ``width_m`` fits in
unseen space it reaches without crossing a wall, through gaps at least that wide (across seen
space too: a ray seen through a door splits a room's unseen space but does not wall it off).
numpy only, besides shapely's point-in-polygon test.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.free_space_grid import disk_offsets, sample_segments
from companion.core.geometry import FloatArray


@dataclass(frozen=True, slots=True)
class SliverParams:
    """How far round a frontier vertex to look, and how wide unseen space must be to count."""

    reach_m: float = 1.0  # the window: this far from the vertex each way (along its normal and across)
    width_m: float = 0.4  # unseen space that no disk this wide fits in, or reaches through, is a sliver
    vicinity_m: float = 0.4  # where the vertex starts: the space this close that no wall parts from it
    cell_m: float = 0.1


def sliver_vertices(
    vertices_xy: FloatArray,
    outward_xy: FloatArray,
    shapes: NDArray[np.object_],
    walls_xy: FloatArray,
    params: SliverParams,
) -> NDArray[np.bool_]:
    """Which vertices (N, 2), with their outward unit normals (N, 2), have only a sliver of unseen
    space about them, given the views' polygons ``shapes`` and their walls (M, 2, 2), all in one
    frame: within ``reach_m``, no disk of ``width_m`` fits in unseen space that the vertex reaches
    without crossing a wall, through gaps at least that wide (across seen space too: a ray seen
    through a door splits the room's unseen space, but does not wall it off)."""
    n = vertices_xy.shape[0]
    out = np.zeros(n, dtype=bool)
    if n == 0 or params.reach_m <= 0.0:
        return out
    cell = params.cell_m
    half = max(1, round(params.reach_m / cell))
    steps = cell * np.arange(-half, half + 1)  # the window: centred on the vertex, along its normal
    side = np.column_stack((-outward_xy[:, 1], outward_xy[:, 0]))
    # (N, rows, cols, 2): every cell centre of every vertex's window
    pts = (
        vertices_xy[:, None, None, :]
        + steps[None, :, None, None] * outward_xy[:, None, None, :]
        + steps[None, None, :, None] * side[:, None, None, :]
    )
    size = steps.size
    wall = _wall_cells(vertices_xy, outward_xy, side, walls_xy, half, cell)
    radius = params.width_m / 2.0 / cell
    disk = disk_offsets(radius)
    # A window without walls whose cells just beyond the vertex hold an unseen disk: open, without
    # rasterising the rest (most frontiers: a range limit in open space).
    probe = np.array([(half + math.ceil(radius) + 1 + dy, half + dx) for dy, dx in disk])
    ask: NDArray[np.bool_] = np.asarray(wall.any(axis=(1, 2)), dtype=bool)
    clear = np.flatnonzero(~ask)
    if clear.size:
        ask[clear] = _inside_any(pts[clear][:, probe[:, 0], probe[:, 1]], shapes).any(axis=1)
    if not ask.any():
        return out
    pts, wall = pts[ask], wall[ask]
    seen = _inside_any(pts.reshape(pts.shape[0], -1, 2), shapes).reshape(-1, size, size)
    open_space = ~wall
    near = np.hypot(steps[:, None], steps[None, :]) <= params.vicinity_m  # (rows, cols)
    # Where the vertex starts: the space about it that no wall parts from it.
    at_vertex = np.zeros((size, size), dtype=bool)
    at_vertex[half - 1 : half + 2, half - 1 : half + 2] = True
    joined = _fill(open_space & at_vertex[None], open_space & near[None])
    passable = _eroded(open_space, radius)  # where a disk of the width keeps off walls
    through = _fill(passable & joined, passable)
    out[ask] = ~(through & _eroded(~seen & open_space, radius)).any(axis=(1, 2))
    return out


def _fill(seeds: NDArray[np.bool_], within: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(N, rows, cols): the cells of ``within`` 4-connected to a seed (seeds outside it dropped)."""
    filled = seeds & within
    while True:
        grown = filled.copy()
        grown[:, 1:, :] |= filled[:, :-1, :]
        grown[:, :-1, :] |= filled[:, 1:, :]
        grown[:, :, 1:] |= filled[:, :, :-1]
        grown[:, :, :-1] |= filled[:, :, 1:]
        grown &= within
        if np.array_equal(grown, filled):
            return filled
        filled = grown


def _eroded(mask: NDArray[np.bool_], radius_cells: float) -> NDArray[np.bool_]:
    """(N, rows, cols): the cells whose disk of ``radius_cells`` lies in the mask (outside the
    window counts as outside the mask)."""
    _, rows, cols = mask.shape
    core = mask.copy()
    for dy, dx in disk_offsets(radius_cells):
        if dy == 0 and dx == 0:
            continue
        shifted = np.zeros_like(mask)
        ys, yd = (slice(0, rows - dy), slice(dy, rows)) if dy >= 0 else (slice(-dy, rows), slice(0, rows + dy))
        xs, xd = (slice(0, cols - dx), slice(dx, cols)) if dx >= 0 else (slice(-dx, cols), slice(0, cols + dx))
        shifted[:, yd, xd] = mask[:, ys, xs]
        core &= shifted
    return core


def _inside_any(points: FloatArray, shapes: NDArray[np.object_]) -> NDArray[np.bool_]:
    """(N, K) points: which lie inside any of the shapes (each shape tests only the windows its
    bounding box meets)."""
    inside = np.zeros(points.shape[:2], dtype=bool)
    if shapes.size == 0:
        return inside
    lo, hi = points.min(axis=1), points.max(axis=1)  # (N, 2) each window's box
    b = shapely.bounds(shapes)  # (S, 4)
    meets = (
        (b[:, None, 0] <= hi[None, :, 0])
        & (b[:, None, 2] >= lo[None, :, 0])
        & (b[:, None, 1] <= hi[None, :, 1])
        & (b[:, None, 3] >= lo[None, :, 1])
    )
    s_idx, v_idx = np.nonzero(meets)
    if s_idx.size == 0:
        return inside
    shapely.prepare(shapes[np.unique(s_idx)])  # each tests a window of points: worth preparing
    hit = shapely.contains_xy(shapes[s_idx][:, None], points[v_idx, :, 0], points[v_idx, :, 1])
    np.logical_or.at(inside, v_idx, hit)
    return inside


def _wall_cells(
    vertices_xy: FloatArray,
    outward_xy: FloatArray,
    side: FloatArray,
    walls_xy: FloatArray,
    half: int,
    cell: float,
) -> NDArray[np.bool_]:
    """(N, size, size): the window cells a wall crosses (walls sampled every half cell)."""
    n = vertices_xy.shape[0]
    size = 2 * half + 1
    out = np.zeros((n, size, size), dtype=bool)
    # Only the walls whose bounding box meets the windows' box.
    reach = (half + 1) * cell * math.sqrt(2.0)
    lo, hi = vertices_xy.min(axis=0) - reach, vertices_xy.max(axis=0) + reach
    walls_xy = walls_xy[np.all((walls_xy.max(axis=1) >= lo) & (walls_xy.min(axis=1) <= hi), axis=1)]
    if walls_xy.shape[0] == 0:
        return out
    samples = sample_segments(walls_xy, cell / 2.0)
    # (N, P): each sample's offset from each vertex, x and y apart (numpy's sums over an axis of
    # two copy through buffers; the same bits).
    dx = samples[None, :, 0] - vertices_xy[:, 0:1]
    dy = samples[None, :, 1] - vertices_xy[:, 1:2]
    u = np.rint((dx * outward_xy[:, 0:1] + dy * outward_xy[:, 1:2]) / cell).astype(np.intp) + half
    w = np.rint((dx * side[:, 0:1] + dy * side[:, 1:2]) / cell).astype(np.intp) + half
    ok = (u >= 0) & (u < size) & (w >= 0) & (w < size)
    who = np.nonzero(ok)[0]
    out[who, u[ok], w[ok]] = True
    return out
