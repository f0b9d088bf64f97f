"""The companion service: inputs in, the exploration loop, setpoints out, and the mission around
it (wait for inputs, take off, explore, land), with a watchdog on every input.

The service knows links only through :mod:`companion.links.base`. It runs the same
:class:`~companion.core.explorer.Explorer` the simulator drives: each new scan, with the newest
odometry, yields the next target, which the link's setpoint stream sends. If an input goes stale or
bad, or anything fails, the vehicle is left to the autopilot's own hold or land mode.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from companion.core.errors import CoreError
from companion.core.explorer import Explorer, ExplorerParams, StepResult
from companion.core.messages import DepthScan, LoopClosure, Odometry, Setpoint
from companion.core.planner import Mode
from companion.errors import CompanionError
from companion.links.base import FlightControl, InputSource

log = logging.getLogger("companion.service")


class MissionState(Enum):
    WAITING_FOR_INPUTS = "waiting_for_inputs"
    TAKING_OFF = "taking_off"
    EXPLORING = "exploring"
    LANDING = "landing"
    HOLDING = "holding"
    DONE = "done"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class ServiceSettings:
    altitude_m: float = 1.5
    input_timeout_s: float = 1.0
    startup_timeout_s: float = 60.0
    max_time_s: float = 1800.0
    on_stop: str = "land"
    progress_period_s: float = 10.0
    # A scan newer than the newest odometry waits this long (wall time) for odometry to reach its
    # stamp (ArduPilot's pose comes in two messages, paired once both are in): the map places a
    # scan by the pose at its own stamp and would otherwise take it a step later.
    scan_odometry_wait_s: float = 0.2


@dataclass
class Health:
    """What the watchdog and the monitor see."""

    state: MissionState = MissionState.WAITING_FOR_INPUTS
    odometry_count: int = 0
    scan_count: int = 0
    loop_closure_count: int = 0
    scans_ahead_of_odometry: int = 0  # scans whose odometry did not come within the wait
    rejected: dict[str, int] = field(default_factory=dict)
    last_odometry_wall_s: float = -math.inf
    last_scan_wall_s: float = -math.inf
    reason: str = ""


StatusHook = Callable[["Service"], None]


class Service:
    """One exploration flight."""

    def __init__(
        self,
        settings: ServiceSettings,
        inputs: list[InputSource],
        control: FlightControl,
        explorer_params: ExplorerParams | None = None,
        on_status: StatusHook | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.inputs = inputs
        self.control = control
        self.explorer = Explorer(explorer_params)
        self.health = Health()
        self.on_status = on_status
        self._clock = clock
        self._odom: Odometry | None = None
        self._first_odom: Odometry | None = None
        self._scan: DepthScan | None = None
        self._new_scan = asyncio.Event()
        self._closures: list[LoopClosure] = []
        self.step_ms: list[float] = []
        self.path_length_m = 0.0
        self.setpoint: Setpoint | None = None
        self.termination = ""
        self._next_progress_s = -math.inf
        self._lost_control = False

    # -- inputs ---------------------------------------------------------------------------------

    def on_odometry(self, odom: Odometry) -> None:
        if not (odom.pose.is_finite() and math.isfinite(odom.stamp_s)):
            self._reject("odometry")
            return
        if self._odom is not None:
            if odom.stamp_s < self._odom.stamp_s and odom.reset_counter == self._odom.reset_counter:
                self._reject("odometry_out_of_order")
                return
            self.path_length_m += math.hypot(odom.pose.x_m - self._odom.pose.x_m, odom.pose.y_m - self._odom.pose.y_m)
        self._odom = odom
        self._first_odom = self._first_odom or odom
        self.health.odometry_count += 1
        self.health.last_odometry_wall_s = self._clock()

    def on_scan(self, scan: DepthScan) -> None:
        self._scan = scan
        self.health.scan_count += 1
        self.health.last_scan_wall_s = self._clock()
        self._new_scan.set()

    def on_loop_closure(self, closure: LoopClosure) -> None:
        if not closure.earlier_to_current.is_finite():
            self._reject("loop_closure")
            return
        self.health.loop_closure_count += 1
        self._closures.append(closure)  # applied by the step, in its thread

    def _reject(self, kind: str) -> None:
        self.health.rejected[kind] = self.health.rejected.get(kind, 0) + 1

    # -- the mission ----------------------------------------------------------------------------

    def _set_state(self, state: MissionState, reason: str = "") -> None:
        if state is not self.health.state:
            log.info("mission: %s%s", state.value, f" ({reason})" if reason else "")
        self.health.state = state
        self.health.reason = reason
        if self.on_status is not None:
            self.on_status(self)

    def _stale(self) -> str:
        now = self._clock()
        limit = self.settings.input_timeout_s
        if now - self.health.last_odometry_wall_s > limit:
            return f"odometry stale for {now - self.health.last_odometry_wall_s:.1f} s"
        if now - self.health.last_scan_wall_s > limit:
            return f"scans stale for {now - self.health.last_scan_wall_s:.1f} s"
        return ""

    async def run(self) -> dict[str, Any]:
        """Fly one exploration; always leaves the vehicle landed or holding. Returns the report."""
        for source in self.inputs:
            source.subscribe(self.on_odometry, self.on_scan, self.on_loop_closure)
        airborne = False
        try:
            await self._wait_for_inputs()
            self._set_state(MissionState.TAKING_OFF)
            assert self._odom is not None
            p = self._odom.pose
            await self.control.take_off(self.settings.altitude_m, Setpoint(p.x_m, p.y_m, p.yaw_rad))
            airborne = True
            self._set_state(MissionState.EXPLORING)
            self.termination = await self._explore()
        except asyncio.CancelledError:
            self.termination = "stopped"
            await self._safe_stop(airborne)
            self._set_state(MissionState.FAILED, "stopped by signal")
            raise
        except Exception as err:  # ours, or a bug: either way the vehicle lands or holds, never left to a timeout
            self.termination = "error"
            if isinstance(err, (CompanionError, CoreError)):
                log.error("%s", err)
                reason = str(err)
            else:
                log.exception("internal error, stopping the flight")
                reason = f"internal error: {err!r}"
            await self._safe_stop(airborne)
            self._set_state(MissionState.FAILED, reason)
            return self.report()
        await self._safe_stop(airborne, land=True)
        self._set_state(MissionState.DONE, self.termination)
        return self.report()

    async def _wait_for_inputs(self) -> None:
        end = self._clock() + self.settings.startup_timeout_s
        while self._odom is None or self._scan is None:
            if self._clock() > end:
                missing = [n for n, v in (("odometry", self._odom), ("scans", self._scan)) if v is None]
                raise CompanionError(f"no {' and no '.join(missing)} within {self.settings.startup_timeout_s:.0f} s")
            await asyncio.sleep(0.05)

    async def _explore(self) -> str:
        assert self._first_odom is not None
        while True:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._new_scan.wait(), self.settings.input_timeout_s)
            self._new_scan.clear()
            stale = self._stale()
            if stale:
                raise CompanionError(f"inputs went stale: {stale}")
            if not self.control.in_control():
                self._lost_control = True
                raise CompanionError("the vehicle left the companion's control (disarmed, crashed or mode changed)")
            scan, self._scan = self._scan, None
            if scan is None:  # the event outlived its scan (taken by the previous step)
                continue
            # A scan arriving during this wait stays for the next step.
            await self._odometry_reaching(scan.stamp_s)
            odom = self._odom
            assert odom is not None
            closures, self._closures = self._closures, []
            # The step runs in a worker thread so the setpoint stream never waits on it.
            result = await asyncio.to_thread(self._step, odom, scan, closures)
            if result.mode is Mode.COMPLETE:
                unreachable = self.explorer.planner.unreachable(self.explorer.map)
                return "unreachable_frontiers_left" if unreachable else "complete"
            self.setpoint = result.setpoint
            self.control.set_target(result.setpoint)
            if self._clock() >= self._next_progress_s:
                self._next_progress_s = self._clock() + self.settings.progress_period_s
                m = self.explorer.map
                log.info(
                    "exploring: %.0f s, %s, %d keyframes, %d open frontier vertices, step p50 %.1f ms",
                    odom.stamp_s - self._first_odom.stamp_s,
                    result.mode.value,
                    len(m),
                    m.open_frontier_count(),
                    float(np.percentile(self.step_ms[-200:], 50)),
                )
            if self.on_status is not None:
                self.on_status(self)
            if odom.stamp_s - self._first_odom.stamp_s > self.settings.max_time_s:
                return "timeout"

    async def _odometry_reaching(self, stamp_s: float) -> None:
        """Give the odometry a moment (``scan_odometry_wait_s``) to reach a scan's stamp, unless
        the scan is further ahead than the explorer would wait for (another clock)."""
        ahead_limit_s = self.explorer.params.scan_odometry_wait_s
        end = self._clock() + self.settings.scan_odometry_wait_s
        while (odom := self._odom) is not None and 1e-6 < stamp_s - odom.stamp_s <= ahead_limit_s:
            if self._clock() >= end:
                self.health.scans_ahead_of_odometry += 1
                return
            await asyncio.sleep(0.002)

    def _step(self, odom: Odometry, scan: DepthScan, closures: list[LoopClosure]) -> StepResult:
        t0 = time.perf_counter()
        for closure in closures:
            self.explorer.add_loop_closure(closure)
        result = self.explorer.step(odom, scan)
        self.step_ms.append((time.perf_counter() - t0) * 1e3)
        return result

    async def _safe_stop(self, airborne: bool, land: bool | None = None) -> None:
        """Leave the vehicle safe through the autopilot's own modes, never by silence. When the
        pilot or the autopilot took the vehicle over, leave it to them."""
        if not airborne or self._lost_control:
            return
        want_land = land if land is not None else self.settings.on_stop == "land"
        self._set_state(MissionState.LANDING if want_land else MissionState.HOLDING)
        actions: list[Callable[[], Awaitable[None]]] = (
            [self.control.land, self.control.hold] if want_land else [self.control.hold, self.control.land]
        )
        for action in actions:
            try:
                await asyncio.shield(action())
                return
            except (CompanionError, asyncio.CancelledError) as err:
                log.error("could not %s: %s", action.__name__, err or "cancelled")

    # -- report ---------------------------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        steps = np.asarray(self.step_ms or [0.0])
        elapsed = 0.0
        if self._odom is not None and self._first_odom is not None:
            elapsed = self._odom.stamp_s - self._first_odom.stamp_s
        return {
            "map": None,  # unknown to the companion: it explores what it finds
            "planner": "polygon",
            "seed": None,
            "coverage": None,  # ground truth is the simulator's (sitl run --report)
            "exploration_time_s": round(elapsed, 3),
            "time_to_99_s": None,
            "time_to_final_coverage_s": None,
            "path_length_m": round(self.path_length_m, 3),
            "collisions": None,
            "termination": self.termination,
            "state": self.health.state.value,
            "reason": self.health.reason,
            **self.explorer.map_counts(),
            "inputs": {
                "odometry": self.health.odometry_count,
                "scans": self.health.scan_count,
                "loop_closures": self.health.loop_closure_count,
                "rejected": dict(self.health.rejected),
                "scans_ahead_of_odometry": self.health.scans_ahead_of_odometry,
            },
            "step_ms": {
                "p50": round(float(np.percentile(steps, 50)), 3),
                "p99": round(float(np.percentile(steps, 99)), 3),
                "max": round(float(steps.max()), 3),
                "count": len(self.step_ms),
            },
        }
