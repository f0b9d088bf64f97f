"""The flight logic of a simulated autopilot: modes, arming, takeoff, landing, offboard / guided
position targets and their failsafes, the way PX4 and ArduPilot Copter behave where it matters
for a companion computer. No I/O: :mod:`sitl.mavlink_vehicle` puts it on the wire.

Behaviour modelled (from the PX4 and ArduPilot documentation):

- PX4 switches to OFFBOARD only while position setpoints arrive (the last within ``COM_OF_LOSS_T``),
  and leaves it after ``COM_OF_LOSS_T`` seconds without one, for the mode ``COM_OBL_RC_ACT`` names (position mode
  without RC sticks falls through to Hold).
- ArduPilot accepts position targets in GUIDED and holds the last one for ever (``GUID_TIMEOUT``
  covers velocity and acceleration targets only); it refuses to arm until its EKF has a position
  estimate, and takes off only on the takeoff command.
- Both disarm on their own after landing, or when armed on the ground without taking off.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from enum import Enum

from companion.core.geometry import Pose2


class Flavour(Enum):
    PX4 = "px4"
    ARDUPILOT = "ardupilot"


# PX4 custom mode: main mode in bits 16-23, sub mode in bits 24-31.
PX4_MODES = {
    "MANUAL": (1, 0),
    "ALTCTL": (2, 0),
    "POSCTL": (3, 0),
    "AUTO.TAKEOFF": (4, 2),
    "AUTO.LOITER": (4, 3),
    "AUTO.MISSION": (4, 4),
    "AUTO.RTL": (4, 5),
    "AUTO.LAND": (4, 6),
    "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0),
}
ARDUPILOT_MODES = {"STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9, "BRAKE": 17}

PX4_PARAMS = {"COM_OF_LOSS_T": 1.0, "COM_OBL_RC_ACT": 0.0, "MIS_TAKEOFF_ALT": 2.5, "COM_DISARM_PRELAND": 10.0}
ARDUPILOT_PARAMS = {"GUID_TIMEOUT": 3.0, "DISARM_DELAY": 10.0, "PILOT_TKOFF_ALT": 0.0}

# COM_OBL_RC_ACT -> the mode PX4 ends up in without RC (position/altitude/manual need sticks).
_PX4_OFFBOARD_LOSS_MODE = {
    0: "AUTO.LOITER",
    1: "AUTO.LOITER",
    2: "AUTO.LOITER",
    3: "AUTO.RTL",
    4: "AUTO.LAND",
    5: "AUTO.LOITER",
}


def px4_custom_mode(name: str) -> int:
    main, sub = PX4_MODES[name]
    return (main << 16) | (sub << 24)


def px4_mode_name(custom_mode: int) -> str | None:
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    for name, (m, s) in PX4_MODES.items():
        if m == main and (s == sub or (m != 4 and s == 0)):
            return name
    return None


class Refused(Exception):
    """A command the autopilot refuses; ``result`` is the MAV_RESULT, ``reason`` its STATUSTEXT."""

    def __init__(self, result: int, reason: str) -> None:
        super().__init__(reason)
        self.result = result
        self.reason = reason


MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_FAILED = 4


@dataclass(frozen=True, slots=True)
class AutopilotParams:
    climb_rate_mps: float = 1.0
    landed_below_m: float = 0.05
    position_estimate_after_s: float = 0.0  # ArduPilot refuses to arm before this (EKF convergence)


@dataclass
class PositionTarget:
    """A position target in the local frame of the estimate: horizontal pose and height (up)."""

    pose: Pose2
    height_m: float


@dataclass
class Autopilot:
    """Modes and flight state of one simulated autopilot; times are simulation seconds."""

    flavour: Flavour
    config: AutopilotParams = field(default_factory=AutopilotParams)
    armed: bool = False
    height_m: float = 0.0
    mode: str = ""
    params: dict[str, float] = field(default_factory=dict)
    target: PositionTarget | None = None  # what the vehicle is flying to now (None: brake, hold)
    last_offboard: PositionTarget | None = None
    setpoint_stamps: deque[float] = field(default_factory=lambda: deque(maxlen=32))
    armed_on_ground_s: float | None = None
    _takeoff_height_m: float | None = None
    _airborne: bool = False
    messages: list[str] = field(default_factory=list)  # STATUSTEXT to send

    def __post_init__(self) -> None:
        if not self.params:
            self.params = dict(PX4_PARAMS if self.flavour is Flavour.PX4 else ARDUPILOT_PARAMS)
        if not self.mode:
            self.mode = "POSCTL" if self.flavour is Flavour.PX4 else "STABILIZE"

    # -- state ----------------------------------------------------------------------------------

    @property
    def landed(self) -> bool:
        return self.height_m <= self.config.landed_below_m

    @property
    def custom_mode(self) -> int:
        if self.flavour is Flavour.PX4:
            return px4_custom_mode(self.mode)
        return ARDUPILOT_MODES[self.mode]

    def mode_for_custom(self, custom_mode: int) -> str | None:
        if self.flavour is Flavour.PX4:
            return px4_mode_name(custom_mode)
        return next((n for n, v in ARDUPILOT_MODES.items() if v == custom_mode), None)

    def _say(self, text: str) -> None:
        self.messages.append(text)

    # -- commands -------------------------------------------------------------------------------

    def arm(self, now_s: float) -> None:
        if self.armed:
            return
        if self.flavour is Flavour.ARDUPILOT:
            if now_s < self.config.position_estimate_after_s:
                raise Refused(MAV_RESULT_FAILED, "PreArm: Need Position Estimate")
            if self.mode not in ("GUIDED", "LOITER", "STABILIZE", "ALT_HOLD"):
                raise Refused(MAV_RESULT_FAILED, f"Arm: Mode not armable ({self.mode})")
        elif self.mode in ("AUTO.LAND", "AUTO.RTL"):
            raise Refused(MAV_RESULT_DENIED, f"Arming denied: not in {self.mode}")
        elif self.mode == "OFFBOARD" and not self._offboard_signal(now_s):
            raise Refused(MAV_RESULT_DENIED, "Arming denied: no offboard signal")
        self.armed = True
        self.armed_on_ground_s = now_s
        self._say("Armed")

    def disarm(self, force: bool = False) -> None:
        if not self.armed:
            return
        if not self.landed and not force:
            raise Refused(MAV_RESULT_DENIED, "Disarming denied: not landed")
        self.armed = False
        self.armed_on_ground_s = None
        self.target = None
        self._say("Disarmed")

    def takeoff(self, now_s: float, height_m: float, here: Pose2) -> None:
        if not self.armed:
            raise Refused(MAV_RESULT_DENIED, "Takeoff denied: disarmed")
        if not math.isfinite(height_m) or height_m <= 0.0:
            height_m = self.params.get("MIS_TAKEOFF_ALT", 2.5)
        if self.flavour is Flavour.ARDUPILOT and self.mode != "GUIDED":
            raise Refused(MAV_RESULT_FAILED, f"Takeoff: not in GUIDED ({self.mode})")
        self._takeoff_height_m = height_m
        self.target = PositionTarget(here, height_m)
        if self.flavour is Flavour.PX4:
            self.mode = "AUTO.TAKEOFF"
        self._say(f"Takeoff to {height_m:.1f} m")

    def land(self, here: Pose2) -> None:
        self.set_mode("AUTO.LAND" if self.flavour is Flavour.PX4 else "LAND", 0.0, here)

    def set_mode(self, name: str, now_s: float, here: Pose2) -> None:
        if name == self.mode:
            return
        if name == "OFFBOARD":
            if not self._offboard_signal(now_s):
                raise Refused(MAV_RESULT_TEMPORARILY_REJECTED, "Switching to OFFBOARD rejected: no offboard signal")
            self.target = self.last_offboard
        elif name in ("POSCTL", "AUTO.LOITER", "LOITER", "BRAKE", "ALT_HOLD", "ALTCTL") or name == "GUIDED":
            self.target = PositionTarget(here, self.height_m)
        elif name in ("AUTO.LAND", "LAND"):
            self.target = PositionTarget(here, 0.0)
        elif name in ("AUTO.RTL", "RTL"):
            self.target = PositionTarget(Pose2(0.0, 0.0, here.yaw_rad), max(self.height_m, 1.0))
        elif name in ("MANUAL", "STABILIZED", "STABILIZE"):
            self.target = PositionTarget(here, self.height_m)  # no sticks: hold
        else:
            raise Refused(MAV_RESULT_DENIED, f"Mode {name} not supported by this vehicle")
        self.mode = name
        self._say(f"Mode {name}")

    def position_target(self, now_s: float, target: PositionTarget) -> None:
        """A SET_POSITION_TARGET_LOCAL_NED arrived."""
        if self.flavour is Flavour.PX4:
            self.setpoint_stamps.append(now_s)
            self.last_offboard = target
            if self.mode == "OFFBOARD":
                self.target = target
        elif self.mode == "GUIDED" and not self.landed:
            self.target = target  # held until the next one, whatever the time since

    def _offboard_signal(self, now_s: float) -> bool:
        """PX4: a setpoint newer than COM_OF_LOSS_T. The docs ask for a stream above 2 Hz; the
        commander's check is this timeout (so MAVSDK's set-then-start works, as on PX4)."""
        loss_s = self.params.get("COM_OF_LOSS_T", 1.0)
        return bool(self.setpoint_stamps) and now_s - self.setpoint_stamps[-1] <= loss_s

    # -- time -----------------------------------------------------------------------------------

    def tick(self, now_s: float, dt_s: float, here: Pose2) -> PositionTarget | None:
        """Advance the mode logic and the height; the horizontal target to fly (None: hold still)."""
        p = self.params
        if self.flavour is Flavour.PX4 and self.mode == "OFFBOARD" and not self._offboard_signal(now_s):
            action = int(p.get("COM_OBL_RC_ACT", 0.0))
            fallback = _PX4_OFFBOARD_LOSS_MODE.get(action, "AUTO.LOITER")
            self._say(f"Offboard signal lost: switching to {fallback}")
            self.set_mode(fallback, now_s, here)
        target = self.target if self.armed else None
        # Height: climb or descend towards the target height.
        goal_h = target.height_m if target is not None else (self.height_m if self.armed else 0.0)
        if not self.armed:
            goal_h = 0.0
        step = self.config.climb_rate_mps * dt_s
        self.height_m = max(0.0, self.height_m + max(-step, min(step, goal_h - self.height_m)))
        takeoff_h = self._takeoff_height_m
        if self.mode == "AUTO.TAKEOFF" and takeoff_h is not None and abs(self.height_m - takeoff_h) < 0.1:
            self.set_mode("AUTO.LOITER", now_s, here)
        if self.mode in ("AUTO.RTL", "RTL") and target is not None and math.hypot(here.x_m, here.y_m) < 0.3:
            self.set_mode("AUTO.LAND" if self.flavour is Flavour.PX4 else "LAND", now_s, here)
        if self.armed and self.landed:
            # Touched down: by a landing mode, or by flying a target at ground level.
            touched_down = self._airborne and target is not None and target.height_m <= 0.0
            landing = self.mode in ("AUTO.LAND", "LAND") or touched_down
            delay = p.get("COM_DISARM_PRELAND", p.get("DISARM_DELAY", 10.0))
            if self.armed_on_ground_s is None:
                self.armed_on_ground_s = now_s
            if landing or (delay > 0 and now_s - self.armed_on_ground_s >= delay):
                self._say("Landed: disarmed" if landing else "Auto-disarmed: no takeoff")
                self.armed = False
                self._airborne = False
                self.target = None
                return None
        elif self.armed:
            self.armed_on_ground_s = None
            self._airborne = self._airborne or self.height_m > 0.3
        if target is None or self.landed:
            return None  # on the ground, nothing moves sideways
        return target
