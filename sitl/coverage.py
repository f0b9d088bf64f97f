"""Ground-truth coverage (thesis 3.2): a grid over the map; a cell is explored when a sensor ray
passes through it. Coverage is explored over observable cells: free cells (no wall crosses them,
not inside an obstacle) connected to the start, i.e. reachable and so observable."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from numpy.typing import NDArray

from companion.core.geometry import FloatArray, Pose2
from sitl.world import World


@dataclass(frozen=True, slots=True)
class GridSpec:
    """A regular grid: cell (i, j) covers x0 + [j, j+1) res, y0 + [i, i+1) res."""

    x0_m: float
    y0_m: float
    resolution_m: float
    rows: int
    cols: int

    @staticmethod
    def covering(world: World, resolution_m: float) -> GridSpec:
        minx, miny, maxx, maxy = world.bounds
        cols = int(np.ceil((maxx - minx) / resolution_m))
        rows = int(np.ceil((maxy - miny) / resolution_m))
        return GridSpec(minx, miny, resolution_m, rows, cols)

    def cell_of(self, xy: FloatArray) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        j = np.floor((xy[:, 0] - self.x0_m) / self.resolution_m).astype(np.intp)
        i = np.floor((xy[:, 1] - self.y0_m) / self.resolution_m).astype(np.intp)
        return i, j

    def centres(self) -> FloatArray:
        jj, ii = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.column_stack(
            (
                (jj.ravel() + 0.5) * self.resolution_m + self.x0_m,
                (ii.ravel() + 0.5) * self.resolution_m + self.y0_m,
            )
        )


def flood_fill(passable: NDArray[np.bool_], seed: tuple[int, int]) -> NDArray[np.bool_]:
    """4-connected region of ``passable`` cells containing ``seed`` (numpy wavefront)."""
    region = np.zeros_like(passable)
    if not passable[seed]:
        return region
    region[seed] = True
    while True:
        grown = region.copy()
        grown[1:, :] |= region[:-1, :]
        grown[:-1, :] |= region[1:, :]
        grown[:, 1:] |= region[:, :-1]
        grown[:, :-1] |= region[:, 1:]
        grown &= passable
        if np.array_equal(grown, region):
            return region
        region = grown


class CoverageGrid:
    """Observable cells of a world, and which of them the sensor's rays have passed through."""

    def __init__(self, world: World, resolution_m: float = 0.2) -> None:
        self.spec = GridSpec.covering(world, resolution_m)
        s = self.spec
        centres = s.centres()
        half = resolution_m / 2.0 * 0.99  # a wall along a cell border does not cross the cell
        boxes = shapely.box(centres[:, 0] - half, centres[:, 1] - half, centres[:, 0] + half, centres[:, 1] + half)
        walls = shapely.multilinestrings(shapely.linestrings(world.walls))
        crossed = shapely.intersects(boxes, walls)
        inside = shapely.contains_xy(world.free, centres[:, 0], centres[:, 1])
        free = (inside & ~crossed).reshape(s.rows, s.cols)
        si, sj = s.cell_of(np.array([[world.start.x_m, world.start.y_m]]))
        self.observable = flood_fill(free, (int(si[0]), int(sj[0])))
        self.observable_count = int(self.observable.sum())
        self.explored = np.zeros_like(self.observable)

    def mark_rays(self, pose: Pose2, bearings_rad: FloatArray, ranges_m: FloatArray) -> None:
        """Mark every cell each ray passes through, from the sensor to its return (or max range)."""
        step = self.spec.resolution_m / 3.0
        n = int(np.ceil(float(np.max(ranges_m)) / step)) + 1
        t = np.linspace(0.0, 1.0, n)
        angles = bearings_rad + pose.yaw_rad
        xs = pose.x_m + np.outer(ranges_m * np.cos(angles), t)
        ys = pose.y_m + np.outer(ranges_m * np.sin(angles), t)
        i, j = self.spec.cell_of(np.column_stack((xs.ravel(), ys.ravel())))
        ok = (i >= 0) & (i < self.spec.rows) & (j >= 0) & (j < self.spec.cols)
        self.explored[i[ok], j[ok]] = True

    @property
    def coverage(self) -> float:
        if self.observable_count == 0:
            return 1.0
        return float(np.count_nonzero(self.explored & self.observable)) / self.observable_count
