"""Pure algorithm core: geometry, scans, pose graph, local-polygon map, frontier planner.

numpy and shapely only; no I/O, no clocks, no globals. Everything here is deterministic.
"""
