"""Pure algorithm core: geometry, scans, pose graph, local-polygon map, frontier planner.

numpy and shapely only; no I/O, no clocks, no globals. Everything here is deterministic.
"""

# numpy loads ``numpy.ma`` on first use, and ``np.unique`` (so ``np.isin`` too) asks it whether
# its input is masked: imported here, that 10-30 ms import happens with the core's, not inside
# the first control step that calls them (seen as the slowest step of a flight, session 58).
import numpy.ma  # noqa: F401
