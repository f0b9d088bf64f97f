"""Run one exploration in-process: a simulated vehicle, a planner, ground-truth coverage, a report.

The polygon planner is the product's own :class:`~companion.core.explorer.Explorer`, driven exactly
as the links drive it (odometry + scan in, setpoint out, loop closures as they are reported). The
grid planner is the perfect-pose baseline.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from companion.core.explorer import Explorer, ExplorerParams
from companion.core.fov_polygon import PolygonParams, returns_xy
from companion.core.geometry import Pose2
from companion.core.messages import Setpoint
from companion.core.obstacle_memory import RecentReturns
from companion.core.planner import PlannerParams
from companion.core.setpoint_lead import LeadParams, limit_lead_facing_memory
from sitl.coverage import CoverageGrid
from sitl.drift import DriftParams
from sitl.grid_explorer import GridExplorer
from sitl.replay import RecordedStep, explorer_step
from sitl.simulation import SensorFrame, SimParams, Simulation
from sitl.world import World

PLANNERS = ("polygon", "grid")
# Coverage this close to where a run ended counts as reached (0.05 % of the map): what a run flies
# after ``time_to_final_coverage_s`` is search that found nothing (docs/benchmarks.md, session 64).
FINAL_COVERAGE_TOLERANCE = 0.0005


class Policy(Protocol):
    """What the runner drives: one frame in, a setpoint out (None when exploration has ended)."""

    def step(self, frame: SensorFrame) -> Setpoint | None: ...

    def summary(self) -> dict[str, Any]: ...


class PolygonPolicy:
    """The product: the local-polygon explorer, fed only what a real vehicle would report."""

    def __init__(self, params: ExplorerParams | None = None, record: bool = False) -> None:
        self.explorer = Explorer(params)
        self.step_ms: list[float] = []
        # With ``record``, every step's input and what it answered, in order: the explorer is
        # deterministic, so these replay the flight's steps exactly (:func:`sitl.replay.replay`).
        self.recorded: list[RecordedStep] | None = [] if record else None

    def step(self, frame: SensorFrame) -> Setpoint | None:
        t0 = time.perf_counter()
        setpoint = explorer_step(self.explorer, frame.odometry, frame.scan, frame.loop_closure)
        self.step_ms.append((time.perf_counter() - t0) * 1e3)
        if self.recorded is not None:
            self.recorded.append((frame.odometry, frame.scan, frame.loop_closure, setpoint))
        return setpoint

    def summary(self) -> dict[str, Any]:
        return dict(self.explorer.map_counts())


class GridPolicy:
    """The perfect-pose grid baseline (it reads the true pose, as in the thesis). Its setpoints
    go through the same lead limit as the product's (the newest scan's returns and the recent
    ones remembered, true frame): the same vehicle, with the same speed limit near what it sees."""

    def __init__(self, world: World) -> None:
        self.explorer = GridExplorer(world.bounds)
        self.step_ms: list[float] = []
        # Its poses are perfect, so remembered returns have not drifted: no margin for it. (With
        # the product's, paths it plans 0.3 m off a wall through a door were held short, and it
        # set their frontiers aside: 3 of 110 runs ended at coverage 0.94-0.96.)
        self.lead = LeadParams(memory_margin_m=0.0)
        explorer = ExplorerParams()
        self._recent = RecentReturns(explorer.obstacle_memory_s, explorer.obstacle_memory_m)
        self._travelled_m = 0.0
        self._last: tuple[float, Pose2] | None = None

    def step(self, frame: SensorFrame) -> Setpoint | None:
        t0 = time.perf_counter()
        pose = frame.true_pose
        if self._last is not None:
            self._travelled_m += math.hypot(pose.x_m - self._last[1].x_m, pose.y_m - self._last[1].y_m)
        sp = self.explorer.step(pose, frame.scan)
        if sp is not None:
            velocity = (0.0, 0.0)
            if self._last is not None and frame.stamp_s > self._last[0]:
                dt = frame.stamp_s - self._last[0]
                velocity = ((pose.x_m - self._last[1].x_m) / dt, (pose.y_m - self._last[1].y_m) / dt)
            returns = pose.apply(returns_xy(frame.scan, PolygonParams().frontier_range_tolerance_m))
            # It remembers recent returns as the product does (a jamb turned out of view still
            # holds the setpoint back), and faces one that alone holds it, to see it again.
            self._recent.forget_seen(frame.scan, pose)
            remembered = self._recent.points_xy()
            self._recent.add(frame.stamp_s, self._travelled_m, returns)
            radius = PlannerParams().body_radius_m
            sp, _ = limit_lead_facing_memory(sp, pose, velocity, returns, radius, self.lead, remembered)
        self._last = (frame.stamp_s, pose)
        self.step_ms.append((time.perf_counter() - t0) * 1e3)
        return sp

    def summary(self) -> dict[str, Any]:
        return {
            "keyframes": 0,
            "loop_closures": 0,
            "loop_closures_matched": 0,
            "odometry_edges_matched": 0,
            "frontiers_left": int(self.explorer.frontier_cells().sum()),
            "frontiers_set_aside": self.explorer.unreachable_frontier_cells() if self.explorer.done else 0,
            "frontiers_closed_on_sight": 0,
            "frontiers_closed_on_surface": 0,
            "frontiers_closed_as_slivers": 0,
            "steps_looking_at_remembered": 0,
            "stalls": 0,
        }


@dataclass
class RunTrace:
    """What a run leaves behind for reports and plots."""

    report: dict[str, Any]
    true_path: list[Pose2] = field(default_factory=list)
    estimated_path: list[Pose2] = field(default_factory=list)
    coverage_over_time: list[tuple[float, float]] = field(default_factory=list)
    keyframe_true_poses: dict[int, Pose2] = field(default_factory=dict)
    coverage: CoverageGrid | None = None
    policy: Policy | None = None
    input_lags_s: list[float] = field(default_factory=list)  # age of each frame when the planner got it


Progress = Callable[[float, float], None]  # (sim time s, coverage)


def run_exploration(
    world: World,
    planner: str = "polygon",
    seed: int = 1,
    noise_scale: float = 1.0,
    max_time_s: float = 1800.0,
    sim_params: SimParams | None = None,
    explorer_params: ExplorerParams | None = None,
    progress: Progress | None = None,
    map_label: str | None = None,
    input_latency_s: float = 0.0,
    record_frames: bool = False,
) -> RunTrace:
    """Explore ``world`` until the planner ends, the vehicle crashes, or ``max_time_s`` passes.

    ``input_latency_s`` hands the planner each frame (scan, odometry, loop closures) that much
    later than it was taken, as a link to a real autopilot and camera does; its setpoints act at
    once. Until the first frame arrives the vehicle holds where it started. ``record_frames``
    keeps the polygon planner's inputs and setpoints (``trace.policy.recorded``) for
    :func:`sitl.replay.replay`."""
    if planner not in PLANNERS:
        raise ValueError(f"planner must be one of {', '.join(PLANNERS)}, got {planner!r}")
    if not (math.isfinite(input_latency_s) and input_latency_s >= 0.0):
        raise ValueError(f"input_latency_s must be finite and >= 0, got {input_latency_s!r}")
    base = sim_params or SimParams()
    scale = 0.0 if planner == "grid" else noise_scale  # the baseline has perfect poses
    d = base.drift
    params = SimParams(
        base.sensor,
        base.vehicle,
        DriftParams(d.sigma_xy_m, d.sigma_yaw_rad, d.step_m, scale, d.velocity_sigma_mps),
        base.slam,
        base.physics_rate_hz,
    )
    sim = Simulation(world, params, seed)
    policy: Policy = PolygonPolicy(explorer_params, record_frames) if planner == "polygon" else GridPolicy(world)
    coverage = CoverageGrid(world)
    trace = RunTrace(report={}, coverage=coverage, policy=policy)
    frame = sim.frame()
    pending: deque[SensorFrame] = deque()  # frames taken, not yet handed to the planner
    start = frame.odometry.pose
    setpoint: Setpoint | None = Setpoint(start.x_m, start.y_m, start.yaw_rad)
    termination = "timeout"
    time_to_99: float | None = None
    gains: list[tuple[float, float]] = []  # (stamp, coverage) at every frame that saw new cells
    next_sample = 0.0
    while True:
        coverage.mark_rays(frame.true_pose, frame.scan.bearings_rad, frame.scan.ranges_m)
        trace.true_path.append(frame.true_pose)
        trace.estimated_path.append(frame.odometry.pose)
        cov = coverage.coverage
        if time_to_99 is None and cov >= 0.99:
            time_to_99 = frame.stamp_s
        if not gains or cov > gains[-1][1]:
            gains.append((frame.stamp_s, cov))
        if frame.stamp_s >= next_sample:
            trace.coverage_over_time.append((frame.stamp_s, cov))
            next_sample += 1.0
            if progress is not None:
                progress(frame.stamp_s, cov)
        pending.append(frame)
        due = frame.stamp_s - input_latency_s + 1e-9
        while pending and pending[0].stamp_s <= due:  # every frame, in order, once it is due
            late = pending.popleft()
            trace.input_lags_s.append(frame.stamp_s - late.stamp_s)
            setpoint = policy.step(late)
            if isinstance(policy, PolygonPolicy):
                for k, kf in policy.explorer.map.keyframes.items():
                    if k not in trace.keyframe_true_poses and kf.stamp_s == late.stamp_s:
                        trace.keyframe_true_poses[k] = late.true_pose
            if setpoint is None:
                break
        if setpoint is None:
            termination = "complete"
            if policy.summary()["frontiers_set_aside"]:
                termination = "unreachable_frontiers_left"
            break
        if sim.crashed:
            termination = "crash"
            break
        if frame.stamp_s >= max_time_s:
            break
        frame = sim.advance(Pose2(setpoint.x_m, setpoint.y_m, setpoint.yaw_rad))
        if sim.crashed:
            termination = "crash"
            break
    trace.coverage_over_time.append((frame.stamp_s, coverage.coverage))
    steps = np.asarray(getattr(policy, "step_ms", [0.0]) or [0.0])
    trace.report = {
        "map": map_label or world.name,
        "planner": planner,
        "seed": seed,
        "noise_scale": scale,
        "coverage": round(coverage.coverage, 5),
        "exploration_time_s": round(frame.stamp_s, 3),
        "time_to_99_s": None if time_to_99 is None else round(time_to_99, 3),
        "time_to_final_coverage_s": round(_time_to_final(gains, coverage.coverage), 3),
        "path_length_m": round(sim.path_length_m, 3),
        "collisions": sim.collisions,
        "input_latency_s": input_latency_s,
        "termination": termination,
        **policy.summary(),
        "step_ms": {
            "p50": round(float(np.percentile(steps, 50)), 3),
            "p99": round(float(np.percentile(steps, 99)), 3),
            "max": round(float(steps.max()), 3),
            "count": int(steps.size),
        },
    }
    return trace


def _time_to_final(gains: list[tuple[float, float]], final: float) -> float:
    """When coverage first came within ``FINAL_COVERAGE_TOLERANCE`` of its final value (coverage
    never falls, so ``gains`` rises)."""
    return next((t for t, c in gains if c >= final - FINAL_COVERAGE_TOLERANCE), 0.0)
