"""The companion's MAVLink link (pymavlink): inputs from the autopilot, the flight handshake, and
the setpoint stream, for PX4 (OFFBOARD) and ArduPilot (GUIDED).

The link speaks as an onboard computer (the vehicle's system id, component 191,
MAV_TYPE_ONBOARD_CONTROLLER). A reader thread hands every message to the asyncio loop, where one
dispatcher converts frames once (NED / FRD to the core's frame) and feeds the handlers. Commands
wait for their COMMAND_ACK with a deadline and raise :class:`CommandRefused` with the autopilot's
STATUSTEXT reasons.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

from companion.core.errors import ScanError
from companion.core.messages import Odometry, Setpoint
from companion.links.base import CommandRefused, LinkError, LoopClosureHandler, OdometryHandler, ScanHandler
from companion.links.frames import core_to_ned, ned_to_core, yaw_from_quaternion
from companion.links.obstacle_distance import ObstacleDistance, decode_scan
from companion.links.pymavlink_loader import load_mavutil

log = logging.getLogger("companion.mavlink")

mavutil = load_mavutil()
mavlink: Any = mavutil.mavlink

COMPANION_COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
POSITION_YAW_TYPE_MASK = 0x9F8  # use x, y, z and yaw; ignore velocity, acceleration, yaw rate
PX4_MAIN_AUTO, PX4_SUB_LOITER, PX4_MAIN_OFFBOARD = 4, 3, 6
ARDUPILOT_GUIDED, ARDUPILOT_LOITER, ARDUPILOT_LAND = 4, 5, 9


def odometry_velocity_ned(child_frame_id: int, vx: float, vy: float, yaw_ned_rad: float) -> tuple[float, float] | None:
    """ODOMETRY's horizontal velocity as (north, east), m/s. Its ``child_frame_id`` names the
    velocity's frame (REP 147): the body (FRD; BODY_NED, deprecated, means the same for
    velocities), turned by the heading, or the local frame the pose is in. Another frame, or a
    NaN (unknown), gives None: the explorer then differences the pose."""
    if not (math.isfinite(vx) and math.isfinite(vy)):
        return None
    if child_frame_id in (mavlink.MAV_FRAME_BODY_FRD, mavlink.MAV_FRAME_BODY_NED):
        c, s = math.cos(yaw_ned_rad), math.sin(yaw_ned_rad)
        return (c * vx - s * vy, s * vx + c * vy)
    if child_frame_id in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD):
        return (vx, vy)
    return None


@dataclass(frozen=True, slots=True)
class MavlinkSettings:
    url: str
    baud: int = 921600
    setpoint_rate_hz: float = 20.0
    altitude_m: float = 1.5
    command_timeout_s: float = 1.0
    command_attempts: int = 3
    arm_timeout_s: float = 90.0
    connect_timeout_s: float = 30.0
    climb_timeout_s: float = 30.0
    land_timeout_s: float = 60.0
    input_rate_hz: float = 10.0


class MavlinkLink:
    """One MAVLink connection to an autopilot: input source and flight control."""

    def __init__(self, settings: MavlinkSettings) -> None:
        self.settings = settings
        self._conn: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._closed = threading.Event()
        self.target_system = 0
        self.target_component = 0
        self.autopilot: str | None = None  # "px4" or "ardupilot"
        self.armed = False
        self.custom_mode = 0
        self.height_m = 0.0
        self._heartbeat = asyncio.Event()
        self._acks: dict[int, asyncio.Future[int]] = {}
        self._reasons: deque[tuple[float, str]] = deque(maxlen=20)
        self._on_odometry: OdometryHandler | None = None
        self._on_scan: ScanHandler | None = None
        self._yaw_ned: float | None = None
        self._attitudes: deque[tuple[float, float]] = deque(maxlen=16)  # (stamp s, yaw NED)
        # LOCAL_POSITION_NED waiting for its heading: stamp, north, east, and its NED velocity.
        self._pending_position: tuple[float, float, float, float, float] | None = None
        self._odometry_seen_s = -math.inf
        self._odom_stamp_s: float | None = None  # vehicle time of the newest odometry
        self._last_input_s: dict[str, float] = {}
        self._target: tuple[float, float, float] | None = None  # north, east, yaw (NED)
        self._tasks: list[asyncio.Task[None]] = []
        self._stream: asyncio.Task[None] | None = None
        self._boot = time.monotonic()
        self.dropped: dict[str, int] = {}
        self._warned: set[str] = set()

    # -- connection -----------------------------------------------------------------------------

    async def connect(self) -> None:
        """Open the connection and wait for the autopilot's heartbeat."""
        self._loop = asyncio.get_running_loop()
        s = self.settings
        end = time.monotonic() + s.connect_timeout_s
        while True:  # a TCP server (ArduPilot SITL) may not be listening yet
            try:
                self._conn = await asyncio.to_thread(
                    mavutil.mavlink_connection,
                    s.url,
                    baud=s.baud,
                    source_system=1,
                    source_component=COMPANION_COMPONENT_ID,
                    autoreconnect=True,
                )
                break
            except (OSError, ValueError, OverflowError) as err:
                if time.monotonic() >= end:
                    raise LinkError(f"cannot open MAVLink connection {s.url!r}: {err}") from None
                if "open" not in self._warned:  # once, not every half second: say why it waits
                    self._warned.add("open")
                    log.warning("cannot open %s yet (%s): retrying for %.0f s", s.url, err, s.connect_timeout_s)
                await asyncio.sleep(0.5)
        self._thread = threading.Thread(target=self._read, name="mavlink-reader", daemon=True)
        self._thread.start()
        self._tasks.append(asyncio.create_task(self._heartbeats()))
        try:
            await asyncio.wait_for(self._heartbeat.wait(), s.connect_timeout_s)
        except TimeoutError:
            raise LinkError(f"no autopilot heartbeat on {s.url} within {s.connect_timeout_s:.0f} s") from None
        self._conn.mav.srcSystem = self.target_system  # speak as a component of the vehicle
        log.info("connected to %s autopilot, system %d", self.autopilot, self.target_system)
        await self._request_streams()
        self._tasks.append(asyncio.create_task(self._keep_streams()))

    def subscribe(
        self,
        on_odometry: OdometryHandler | None = None,
        on_scan: ScanHandler | None = None,
        on_loop_closure: LoopClosureHandler | None = None,
    ) -> None:
        """MAVLink carries odometry and scans; it has no loop-closure message."""
        if on_odometry is not None:
            self._on_odometry = on_odometry
        if on_scan is not None:
            self._on_scan = on_scan

    async def close(self) -> None:
        for task in [*self._tasks, *([self._stream] if self._stream else [])]:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks.clear()
        self._stream = None
        self._closed.set()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 1.0)
        if self._conn is not None:
            self._conn.close()

    # -- receiving ------------------------------------------------------------------------------

    def _read(self) -> None:
        assert self._loop is not None
        while not self._closed.is_set():
            try:
                msg = self._conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError) as err:
                log.debug("read error: %s", err)
                time.sleep(0.05)
                continue
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            try:
                self._loop.call_soon_threadsafe(self._dispatch, msg)
            except RuntimeError:  # the loop has closed
                return

    def _drop(self, kind: str, why: str) -> None:
        self.dropped[kind] = self.dropped.get(kind, 0) + 1
        if kind not in self._warned:
            self._warned.add(kind)
            log.warning("dropping bad %s: %s (logged once; counted)", kind, why)

    def _dispatch(self, msg: Any) -> None:
        kind = msg.get_type()
        src = msg.get_srcSystem()
        if kind == "HEARTBEAT":
            self._heartbeat_from(msg)
            return
        if not self._heartbeat.is_set() or src != self.target_system:
            return
        now = time.monotonic()
        if kind == "ODOMETRY":
            self._odometry(msg, now)
        elif kind == "LOCAL_POSITION_NED":
            self.height_m = -float(msg.z)
            if now - self._odometry_seen_s > 1.0:
                p = (msg.time_boot_ms / 1e3, float(msg.x), float(msg.y), float(msg.vx), float(msg.vy))
                self._pending_position = p
                self._pair_position_with_attitude(now)
        elif kind == "ATTITUDE":
            if math.isfinite(msg.yaw):
                self._yaw_ned = float(msg.yaw)
                self._attitudes.append((msg.time_boot_ms / 1e3, float(msg.yaw)))
                self._pair_position_with_attitude(now)
        elif kind == "OBSTACLE_DISTANCE":
            self._scan(msg, now)
        elif kind == "COMMAND_ACK":
            fut = self._acks.get(int(msg.command))
            if fut is not None and not fut.done():
                if msg.result == mavlink.MAV_RESULT_IN_PROGRESS:
                    return
                fut.set_result(int(msg.result))
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else msg.text.decode(errors="replace")
            self._reasons.append((now, text))
            level = logging.WARNING if msg.severity <= mavlink.MAV_SEVERITY_WARNING else logging.INFO
            log.log(level, "autopilot: %s", text)

    def _heartbeat_from(self, msg: Any) -> None:
        if msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID or msg.type in (
            mavlink.MAV_TYPE_GCS,
            mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
        ):
            return
        if not self._heartbeat.is_set():
            self.target_system = msg.get_srcSystem()
            self.target_component = msg.get_srcComponent()
            self.autopilot = "px4" if msg.autopilot == mavlink.MAV_AUTOPILOT_PX4 else "ardupilot"
            self._heartbeat.set()
        if msg.get_srcSystem() == self.target_system and msg.get_srcComponent() == self.target_component:
            self.armed = bool(msg.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.custom_mode = int(msg.custom_mode)

    def _pair_position_with_attitude(self, now: float) -> None:
        """Odometry from LOCAL_POSITION_NED and the heading at the same instant (interpolated
        between ATTITUDE samples), so a turn does not skew the pose; waits for the attitude."""
        if self._pending_position is None or not self._attitudes:
            return
        stamp, north, east, v_north, v_east = self._pending_position
        newest_t, newest_yaw = self._attitudes[-1]
        if newest_t < stamp and stamp - newest_t < 0.2:
            return  # the attitude for this instant has not arrived yet
        yaw = newest_yaw
        for (t0, y0), (t1, y1) in zip(list(self._attitudes)[:-1], list(self._attitudes)[1:], strict=True):
            if t0 <= stamp <= t1:
                w = 0.0 if t1 == t0 else (stamp - t0) / (t1 - t0)
                yaw = y0 + w * math.remainder(y1 - y0, 2.0 * math.pi)
                break
        self._pending_position = None
        self._publish_odometry(stamp, north, east, yaw, 0, now, (v_north, v_east))

    def _odometry(self, msg: Any, now: float) -> None:
        if msg.frame_id not in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_LOCAL_FRD):
            self._drop("ODOMETRY", f"frame {msg.frame_id} is not a local frame")
            return
        q = msg.q
        values = (msg.x, msg.y, msg.z, *q)
        if not all(math.isfinite(v) for v in values):
            self._drop("ODOMETRY", "non-finite pose")
            return
        norm = math.sqrt(sum(v * v for v in q))
        if abs(norm - 1.0) > 0.1:  # all zeros (unset) read as heading north: a wrong pose, not a pose
            self._drop("ODOMETRY", f"the attitude quaternion's norm is {norm:.2f}, not 1")
            return
        self._odometry_seen_s = now
        self.height_m = -float(msg.z)
        yaw = yaw_from_quaternion(q[0], q[1], q[2], q[3])
        self._yaw_ned = yaw
        velocity = odometry_velocity_ned(msg.child_frame_id, float(msg.vx), float(msg.vy), yaw)
        self._publish_odometry(msg.time_usec / 1e6, msg.x, msg.y, yaw, int(msg.reset_counter), now, velocity)

    def _publish_odometry(
        self,
        stamp_s: float,
        north: float,
        east: float,
        yaw_ned: float,
        reset: int,
        now: float,
        velocity_ned: tuple[float, float] | None = None,
    ) -> None:
        if not all(math.isfinite(v) for v in (stamp_s, north, east, yaw_ned)):
            self._drop("odometry", "non-finite value")
            return
        self._last_input_s["odometry"] = now
        self._odom_stamp_s = stamp_s
        if self._on_odometry is not None:
            velocity = None
            if velocity_ned is not None and all(math.isfinite(v) for v in velocity_ned):
                velocity = (velocity_ned[1], velocity_ned[0])  # core axes: x east, y north
            self._on_odometry(Odometry(stamp_s, ned_to_core(north, east, yaw_ned), reset, velocity))

    def _scan(self, msg: Any, now: float) -> None:
        od = ObstacleDistance(
            int(msg.time_usec),
            tuple(int(d) for d in msg.distances),
            float(msg.increment_f) if msg.increment_f > 0 else float(msg.increment),
            float(msg.angle_offset),
            int(msg.min_distance),
            int(msg.max_distance),
            int(msg.frame),
        )
        stamp = od.time_usec / 1e6
        odom_stamp = self._odom_stamp_s
        if odom_stamp is not None and abs(stamp - odom_stamp) > 5.0:
            # Another clock (UNIX time against time since boot): pair with the newest odometry.
            stamp = odom_stamp
        try:
            scan = decode_scan(od, stamp, self._yaw_ned)
        except ScanError as err:
            self._drop("OBSTACLE_DISTANCE", str(err))
            return
        self._last_input_s["scan"] = now
        if self._on_scan is not None:
            self._on_scan(scan)

    def input_age_s(self, name: str) -> float:
        """Wall seconds since the last good ``odometry`` or ``scan`` (inf if none yet)."""
        return time.monotonic() - self._last_input_s.get(name, -math.inf)

    # -- sending --------------------------------------------------------------------------------

    async def _heartbeats(self) -> None:
        while True:
            self._conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )
            await asyncio.sleep(1.0)

    async def command(self, name: str, command: int, *params: float, attempts: int | None = None) -> None:
        """COMMAND_LONG, re-sent (with ``confirmation`` counting up) until acknowledged."""
        p = [*params, *([0.0] * (7 - len(params)))]
        loop = asyncio.get_running_loop()
        sent_at = time.monotonic()
        for confirmation in range(attempts or self.settings.command_attempts):
            fut: asyncio.Future[int] = loop.create_future()
            self._acks[command] = fut
            self._conn.mav.command_long_send(self.target_system, self.target_component, command, confirmation, *p)
            try:
                result = await asyncio.wait_for(fut, self.settings.command_timeout_s)
            except TimeoutError:
                continue
            finally:
                self._acks.pop(command, None)
            if result == mavlink.MAV_RESULT_ACCEPTED:
                return
            reasons = [text for t, text in self._reasons if t >= sent_at - 0.05]
            result_name = (
                mavlink.enums["MAV_RESULT"][result].name if result in mavlink.enums["MAV_RESULT"] else str(result)
            )
            raise CommandRefused(name, result_name, reasons)
        raise CommandRefused(name, "no COMMAND_ACK", [text for t, text in self._reasons if t >= sent_at])

    async def _request_streams(self) -> None:
        """Ask for what the link needs; ArduPilot refuses ODOMETRY (it has none): then the link
        builds odometry from LOCAL_POSITION_NED and ATTITUDE."""
        hz = self.settings.input_rate_hz
        wanted = [
            ("LOCAL_POSITION_NED", mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, hz),
            ("ATTITUDE", mavlink.MAVLINK_MSG_ID_ATTITUDE, hz),
            ("OBSTACLE_DISTANCE", mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE, hz),
        ]
        if self.autopilot == "px4":
            wanted.insert(0, ("ODOMETRY", mavlink.MAVLINK_MSG_ID_ODOMETRY, hz))
        for name, msg_id, rate in wanted:
            try:
                await self.command(
                    f"SET_MESSAGE_INTERVAL {name}", mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / rate
                )
            except CommandRefused as err:
                log.info("%s", err)

    async def _keep_streams(self) -> None:
        """Re-request the streams when inputs stop arriving (early requests after boot can be lost)."""
        while True:
            await asyncio.sleep(2.0)
            # Only the inputs taken from this link (scans may come from a camera on Zenoh).
            odometry_missing = self._on_odometry is not None and self.input_age_s("odometry") > 2.0
            scans_missing = self._on_scan is not None and self.input_age_s("scan") > 2.0
            if odometry_missing or scans_missing:
                await self._request_streams()

    # -- flight control -------------------------------------------------------------------------

    def set_target(self, setpoint: Setpoint) -> None:
        if not setpoint.is_finite():
            raise LinkError(f"refusing a non-finite setpoint {setpoint}")
        self._target = core_to_ned(setpoint.x_m, setpoint.y_m, setpoint.yaw_rad)

    def _start_stream(self) -> None:
        if self._stream is None:
            self._stream = asyncio.create_task(self._stream_setpoints())

    async def _stop_stream(self) -> None:
        if self._stream is not None:
            self._stream.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._stream
            self._stream = None

    async def _stream_setpoints(self) -> None:
        period = 1.0 / self.settings.setpoint_rate_hz
        down = -self.settings.altitude_m
        next_t = time.monotonic()
        while True:
            if self._target is not None:
                north, east, yaw = self._target
                self._conn.mav.set_position_target_local_ned_send(
                    int((time.monotonic() - self._boot) * 1000) & 0xFFFFFFFF,
                    self.target_system,
                    self.target_component,
                    mavlink.MAV_FRAME_LOCAL_NED,
                    POSITION_YAW_TYPE_MASK,
                    north,
                    east,
                    down,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    0.0,
                    yaw,
                    0.0,
                )
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))

    async def _set_mode(self, name: str, main: int, sub: int = 0) -> None:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        await self.command(f"set mode {name}", mavlink.MAV_CMD_DO_SET_MODE, base, main, sub)

    async def take_off(self, altitude_m: float, hold: Setpoint) -> None:
        self.set_target(hold)
        if self.autopilot == "px4":
            # PX4: OFFBOARD is accepted only once setpoints stream; arming then climbs to them.
            self._start_stream()
            await asyncio.sleep(max(0.5, 5.0 / self.settings.setpoint_rate_hz))
            await self._retry_until(self.settings.arm_timeout_s, lambda: self._set_mode("OFFBOARD", PX4_MAIN_OFFBOARD))
            await self._retry_until(self.settings.arm_timeout_s, self._arm)
        else:
            # ArduPilot: GUIDED, arm (refused until the EKF has a position), takeoff command.
            await self._set_mode("GUIDED", ARDUPILOT_GUIDED)
            await self._retry_until(self.settings.arm_timeout_s, self._arm)
            await self.command("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, 0, 0, altitude_m)
        await self._wait_for(lambda: self.height_m >= altitude_m - 0.2, self.settings.climb_timeout_s, "climb")
        self._start_stream()

    def in_control(self) -> bool:
        if self.autopilot == "px4":
            return self.armed and self.custom_mode == PX4_MAIN_OFFBOARD << 16
        return self.armed and self.custom_mode == ARDUPILOT_GUIDED

    async def _arm(self) -> None:
        await self.command("arm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)

    async def _retry_until(self, deadline_s: float, action: Any) -> None:
        """Retry an action the autopilot refuses for now (arming before its estimator converged)."""
        end = time.monotonic() + deadline_s
        while True:
            try:
                await action()
                return
            except CommandRefused as err:
                if time.monotonic() >= end:
                    raise
                log.info("%s; retrying", err)
                await asyncio.sleep(1.0)

    async def _wait_for(self, condition: Any, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() >= end:
                raise LinkError(f"{what} did not finish within {timeout_s:.0f} s")
            await asyncio.sleep(0.05)

    async def hold(self) -> None:
        if self.autopilot == "px4":
            await self._set_mode("HOLD", PX4_MAIN_AUTO, PX4_SUB_LOITER)
        else:
            await self._set_mode("LOITER", ARDUPILOT_LOITER)
        await self._stop_stream()

    async def land(self) -> None:
        if self.autopilot == "px4":
            await self.command("land", mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        else:
            await self._set_mode("LAND", ARDUPILOT_LAND)
        await self._stop_stream()
        await self._wait_for(lambda: not self.armed, self.settings.land_timeout_s, "landing")
