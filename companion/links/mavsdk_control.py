"""Flight control through MAVSDK-Python 4.x (``control: mavsdk``), for PX4 users who prefer it.

MAVSDK's Offboard plugin streams the position + yaw setpoint itself (20 Hz); this adapter only
replaces it. Inputs still come through pymavlink or Zenoh. MAVSDK keeps re-sending the last
setpoint for ever, so stopping always goes through the autopilot's own hold or land mode.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any

from companion.core.messages import Setpoint
from companion.links.base import CommandRefused, LinkError
from companion.links.frames import core_to_ned

log = logging.getLogger("companion.mavsdk")


class MavsdkControl:
    """Offboard position control of one vehicle through MAVSDK."""

    def __init__(self, url: str, altitude_m: float, timeout_s: float = 30.0) -> None:
        self.url = url
        self.altitude_m = altitude_m
        self.timeout_s = timeout_s
        self._mavsdk: Any = None
        self._system: Any = None
        self._offboard: Any = None
        self._action: Any = None
        self._telemetry: Any = None
        self._target: Any = None
        self._pending: asyncio.Task[None] | None = None
        self._watcher: asyncio.Task[None] | None = None
        self._armed: bool | None = None  # None until MAVSDK reports it
        self._offboard_mode: bool | None = None

    async def connect(self) -> None:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        config = Configuration.create_with_component_type(ComponentType.COMPANION_COMPUTER)
        self._mavsdk = Mavsdk(config)
        await self._mavsdk.add_any_connection(self.url)
        self._system = await self._mavsdk.first_autopilot(timeout_s=self.timeout_s)
        if self._system is None:
            raise LinkError(f"MAVSDK found no autopilot on {self.url} within {self.timeout_s:.0f} s")
        self._offboard = OffboardAsync(self._system)
        self._action = ActionAsync(self._system)
        self._telemetry = TelemetryAsync(self._system)
        self._watcher = asyncio.create_task(self._watch())
        log.info("MAVSDK connected on %s", self.url)

    def _position(self, setpoint: Setpoint) -> Any:
        from mavsdk.asyncio.plugins.offboard import PositionNedYaw

        north, east, yaw = core_to_ned(setpoint.x_m, setpoint.y_m, setpoint.yaw_rad)
        return PositionNedYaw(north, east, -self.altitude_m, math.degrees(yaw))

    async def _call(self, what: str, coro: Any) -> None:
        try:
            await coro
        except Exception as err:  # MAVSDK raises its own error type per plugin
            raise CommandRefused(what, type(err).__name__, [str(err)]) from None

    async def take_off(self, altitude_m: float, hold: Setpoint) -> None:
        self._target = self._position(hold)
        await self._call("set first setpoint", self._offboard.set_position_ned(self._target))
        await self._call("start offboard", self._offboard.start())
        end = time.monotonic() + self.timeout_s
        while True:
            try:
                await self._call("arm", self._action.arm())
                break
            except CommandRefused as err:
                if time.monotonic() > end:
                    raise
                log.info("%s; retrying", err)
                await asyncio.sleep(1.0)
        async for pv in self._telemetry.subscribe_position_velocity_ned():
            if -pv.position.down_m >= altitude_m - 0.2:
                break
            if time.monotonic() > end:
                raise LinkError("climb did not finish in time")

    def in_control(self) -> bool:
        return self._armed is not False and self._offboard_mode is not False

    async def _watch(self) -> None:
        """Armed state and flight mode, as MAVSDK reports them (its offboard.is_active() can stay
        True when the vehicle left the mode, so trust the telemetry instead)."""

        async def armed() -> None:
            async for value in self._telemetry.subscribe_armed():
                self._armed = bool(value)

        async def mode() -> None:
            async for value in self._telemetry.subscribe_flight_mode():
                offboard = _flight_mode_name(value) == "OFFBOARD"
                if offboard != self._offboard_mode:
                    log.info("MAVSDK flight mode: %s", value)
                self._offboard_mode = offboard

        await asyncio.gather(armed(), mode())

    def set_target(self, setpoint: Setpoint) -> None:
        if not setpoint.is_finite():
            raise LinkError(f"refusing a non-finite setpoint {setpoint}")
        self._target = self._position(setpoint)
        if self._pending is None or self._pending.done():
            self._pending = asyncio.ensure_future(self._offboard.set_position_ned(self._target))

    async def hold(self) -> None:
        await self._call("hold", self._action.hold())

    async def land(self) -> None:
        await self._call("land", self._action.land())
        end = time.monotonic() + 120.0
        async for armed in self._telemetry.subscribe_armed():
            if not armed or time.monotonic() > end:
                break

    async def close(self) -> None:
        for task in (self._pending, self._watcher):
            if task is not None and not task.done():
                task.cancel()
        if self._mavsdk is not None:
            self._mavsdk.destroy()
            self._mavsdk = None


def _flight_mode_name(value: Any) -> str:
    """MAVSDK 4 yields the FlightMode enum or its integer value."""
    from mavsdk.plugins.telemetry import FlightMode

    try:
        return FlightMode(int(value)).name
    except (TypeError, ValueError):
        return str(value).rsplit(".", 1)[-1].upper()
