import math

import numpy as np

from companion.core.geometry import Pose2
from sitl.coverage import CoverageGrid
from sitl.runner import run_exploration
from sitl.world import load_world
from tests.conftest import square, write_map


def test_observable_cells_exclude_walls_and_obstacle_interiors(tmp_path):
    # 4 x 4 m room, 1 x 1 m block: at 0.5 m cells, walls cross the edge rings of cells.
    w = load_world(write_map(tmp_path / "m.geojson", square(0, 0, 4, 4), [square(1.5, 1.5, 2.5, 2.5)], (0.7, 0.7)))
    grid = CoverageGrid(w, resolution_m=0.5)
    assert grid.spec.rows == 8 and grid.spec.cols == 8
    # The walls run along cell borders, so only the 2 x 2 cells inside the block are excluded.
    assert grid.observable_count == 64 - 4
    assert grid.coverage == 0.0


def test_rays_mark_the_cells_they_pass_through(tmp_path):
    w = load_world(write_map(tmp_path / "m.geojson", square(0, 0, 10, 2), [], (0.5, 1.0)))
    grid = CoverageGrid(w, resolution_m=1.0)
    grid.mark_rays(Pose2(0.5, 1.2, 0.0), np.array([0.0]), np.array([5.0]))
    assert grid.explored[1, :6].all() and not grid.explored[1, 6:].any()
    assert math.isclose(grid.coverage, 6 / grid.observable_count)


def test_grid_baseline_reaches_full_coverage_on_a_small_map(small_room):
    trace = run_exploration(load_world(small_room), "grid", seed=3, max_time_s=400)
    r = trace.report
    assert r["termination"] == "complete"
    assert r["coverage"] >= 0.99
    assert r["collisions"] == 0
