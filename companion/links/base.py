"""What the service needs from a transport, as small interfaces, and the errors links raise.

The service is written against these and never imports pymavlink, MAVSDK or zenoh: a link is
picked by the config and handed in.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from companion.core.messages import DepthScan, LoopClosure, Odometry, Setpoint
from companion.errors import CompanionError

OdometryHandler = Callable[[Odometry], None]
ScanHandler = Callable[[DepthScan], None]
LoopClosureHandler = Callable[[LoopClosure], None]


class LinkError(CompanionError):
    """A transport failed: cannot connect, no answer, lost."""


class CommandRefused(LinkError):
    """The autopilot answered a command with anything but success."""

    def __init__(self, command: str, result: str, reasons: list[str]) -> None:
        why = f" ({'; '.join(reasons)})" if reasons else ""
        super().__init__(f"autopilot refused {command}: {result}{why}")
        self.command = command
        self.result = result
        self.reasons = reasons


class InputSource(Protocol):
    """Delivers odometry, scans and/or loop closures to the handlers given (from the event loop)."""

    def subscribe(
        self,
        on_odometry: OdometryHandler | None = None,
        on_scan: ScanHandler | None = None,
        on_loop_closure: LoopClosureHandler | None = None,
    ) -> None: ...


class FlightControl(Protocol):
    """The flight handshake and the setpoint stream to an autopilot."""

    async def take_off(self, altitude_m: float, hold: Setpoint) -> None:
        """Arm, get airborne at ``altitude_m`` above the local origin, holding ``hold``."""
        ...

    def set_target(self, setpoint: Setpoint) -> None:
        """Replace the target that the stream sends (non-finite targets are refused)."""
        ...

    def in_control(self) -> bool:
        """True while the vehicle is armed and in the mode that follows the companion's targets
        (a crash, a pilot taking over or an autopilot failsafe makes it False)."""
        ...

    async def hold(self) -> None:
        """Stop flying to targets: the autopilot's own position-hold mode."""
        ...

    async def land(self) -> None:
        """Land through the autopilot's landing mode and wait until disarmed on the ground."""
        ...

    async def close(self) -> None: ...
