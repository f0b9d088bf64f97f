"""Replay a recorded flight into a fresh explorer, with no simulator, and time each step.

The explorer is deterministic: fed the frames a flight gave it (odometry, scan and any loop
closure, in order) it answers every step with the flight's setpoint, so replaying them times the
flight's very steps without the simulator or the flight's noise (``benchmarks/step_replay.py``).
This module imports only the explorer's stable interface, so the bench can load it by path
against another checkout's ``companion`` and time that code on the same frames.
"""

from __future__ import annotations

import time

from companion.core.explorer import Explorer, ExplorerParams
from companion.core.messages import DepthScan, LoopClosure, Odometry, Setpoint
from companion.core.planner import Mode

# One step's input and the flight's answer to it (None: exploration had ended).
RecordedStep = tuple[Odometry, DepthScan, LoopClosure | None, Setpoint | None]


def explorer_step(
    explorer: Explorer, odometry: Odometry, scan: DepthScan, loop_closure: LoopClosure | None
) -> Setpoint | None:
    """One step of the product: loop closure, odometry and scan in, setpoint out (None once
    exploration has ended)."""
    if loop_closure is not None:
        explorer.add_loop_closure(loop_closure)
    result = explorer.step(odometry, scan)
    return None if result.mode is Mode.COMPLETE else result.setpoint


def replay(recorded: list[RecordedStep], params: ExplorerParams | None = None) -> tuple[list[float], bool]:
    """Feed the recorded steps to a fresh explorer: each step's time (ms), and whether every
    setpoint was the flight's."""
    explorer = Explorer(params)
    times_ms: list[float] = []
    same = True
    for odometry, scan, loop_closure, flown in recorded:
        t0 = time.perf_counter()
        setpoint = explorer_step(explorer, odometry, scan, loop_closure)
        times_ms.append((time.perf_counter() - t0) * 1e3)
        same = same and setpoint == flown
    return times_ms, same
