"""The simulated vehicle on the wire: the in-process simulator behind a MAVLink 2 autopilot
endpoint that presents itself like PX4 SITL or ArduPilot SITL.

One loop, paced by the simulation clock (``speedup`` times faster than wall time): read what
arrived, step the autopilot's mode logic and the physics by one sensor period, send the streams
that are due. Message timestamps are simulation time since boot, so they stay consistent at any
speed-up. Message semantics follow the MAVLink common set; where PX4 and ArduPilot differ (mode
encoding, default streams, ODOMETRY support) each flavour behaves as the real one does.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from companion.core.geometry import Pose2
from companion.links.frames import core_to_ned, quaternion_from_yaw
from companion.links.obstacle_distance import encode_scan
from companion.links.pymavlink_loader import load_mavutil
from sitl.autopilot import Autopilot, AutopilotParams, Flavour, PositionTarget, Refused
from sitl.coverage import CoverageGrid
from sitl.drift import DriftParams
from sitl.simulation import SensorFrame, SimParams, Simulation
from sitl.world import World

log = logging.getLogger("sitl.vehicle")

mavutil = load_mavutil()
mavlink: Any = mavutil.mavlink

DEFAULT_URL = {Flavour.PX4: "udpout:127.0.0.1:14540", Flavour.ARDUPILOT: "tcpin:127.0.0.1:5760"}
HOME_LAT_DEG, HOME_LON_DEG, HOME_ALT_M = 47.397742, 8.545594, 488.0  # PX4 SITL's default home
EARTH_RADIUS_M = 6_371_000.0

# Streams (message id -> default rate Hz). PX4 streams a default set on its onboard link;
# ArduPilot sends only HEARTBEAT until asked (SET_MESSAGE_INTERVAL or REQUEST_DATA_STREAM).
PX4_DEFAULT_STREAMS = {
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 10.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 10.0,
    mavlink.MAVLINK_MSG_ID_ODOMETRY: 10.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE: 10.0,
}
ARDUPILOT_DEFAULT_STREAMS = {mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE: 10.0}  # the depth camera's own
SUPPORTED_STREAMS = set(PX4_DEFAULT_STREAMS)


@dataclass(frozen=True, slots=True)
class VehicleOptions:
    flavour: Flavour
    urls: tuple[str, ...]
    speedup: float = 1.0
    seed: int = 1
    noise_scale: float = 1.0
    system_id: int = 1
    max_time_s: float | None = None
    position_estimate_after_s: float = 2.0


class MavlinkVehicle:
    """The simulator as a MAVLink autopilot on one or more endpoints."""

    def __init__(self, world: World, options: VehicleOptions, sim_params: SimParams | None = None) -> None:
        self.world = world
        self.options = options
        base = sim_params or SimParams()
        d = base.drift
        params = SimParams(
            base.sensor,
            base.vehicle,
            DriftParams(d.sigma_xy_m, d.sigma_yaw_rad, d.step_m, options.noise_scale, d.velocity_sigma_mps),
            base.slam,
            base.physics_rate_hz,
        )
        self.sim = Simulation(world, params, options.seed)
        self.autopilot = Autopilot(
            options.flavour, AutopilotParams(position_estimate_after_s=options.position_estimate_after_s)
        )
        self.coverage = CoverageGrid(world)
        self.start = world.start
        self.links = [
            mavutil.mavlink_connection(url, source_system=options.system_id, source_component=1, autoreconnect=True)
            for url in options.urls
        ]
        defaults = PX4_DEFAULT_STREAMS if options.flavour is Flavour.PX4 else ARDUPILOT_DEFAULT_STREAMS
        self.intervals_s: dict[int, float] = {k: 1.0 / hz for k, hz in defaults.items()}
        self._next_send: dict[int, float] = {}
        self._next_heartbeat_s = 0.0
        self.frame: SensorFrame = self.sim.frame()
        self.loop_closures: list[Any] = []
        self.on_frame: Callable[[SensorFrame], None] | None = None  # e.g. the Zenoh publisher
        self._stop = False

    # -- pose conversions -----------------------------------------------------------------------

    def _local(self, estimate: Pose2) -> Pose2:
        """The estimate relative to where the autopilot booted (its local origin), in map axes."""
        s = self.start
        return Pose2(estimate.x_m - s.x_m, estimate.y_m - s.y_m, estimate.yaw_rad)

    @property
    def local_estimate(self) -> Pose2:
        """The vehicle's estimate in its local frame (the frame of LOCAL_POSITION_NED, in core axes)."""
        return self._local(self.frame.odometry.pose)

    def _from_local(self, local: Pose2) -> Pose2:
        s = self.start
        return Pose2(local.x_m + s.x_m, local.y_m + s.y_m, local.yaw_rad)

    # -- the loop -------------------------------------------------------------------------------

    def stop(self) -> None:
        self._stop = True

    def run(self) -> None:
        period_s = 1.0 / self.sim.params.sensor.rate_hz
        wall0 = time.monotonic()
        while not self._stop:
            if self.options.max_time_s is not None and self.sim.time_s >= self.options.max_time_s:
                break
            self._receive()
            self._step(period_s)
            self._send_due()
            wall_due = wall0 + self.sim.time_s / self.options.speedup
            delay = wall_due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        for link in self.links:
            link.close()

    def _step(self, period_s: float) -> None:
        ap = self.autopilot
        here = self.frame.odometry.pose
        local_here = self._local(here)
        messages_before = len(ap.messages)
        target = ap.tick(self.sim.time_s, period_s, local_here)
        self.frame = self.sim.advance(None if target is None else self._from_local(target.pose))
        if self.sim.crashed and ap.armed:
            ap.disarm(force=True)
            ap.height_m = 0.0
            self.sim.vehicle.velocity[:] = 0.0
            self._statustext("Collision: vehicle crashed", mavlink.MAV_SEVERITY_CRITICAL)
        for text in ap.messages[messages_before:]:
            self._statustext(text)
        del ap.messages[:]
        f = self.frame
        if not ap.landed:
            self.coverage.mark_rays(f.true_pose, f.scan.bearings_rad, f.scan.ranges_m)
        if f.loop_closure is not None:
            self.loop_closures.append(f.loop_closure)
        if self.on_frame is not None:
            self.on_frame(f)

    # -- receiving ------------------------------------------------------------------------------

    def _receive(self) -> None:
        for link in self.links:
            while True:
                msg = link.recv_msg()
                if msg is None:
                    break
                try:
                    self._handle(link, msg)
                except Exception:  # a bad message must never stop the vehicle
                    log.exception("while handling %s", msg.get_type())

    def _for_us(self, msg: Any) -> bool:
        return getattr(msg, "target_system", 0) in (0, self.options.system_id)

    def _handle(self, link: Any, msg: Any) -> None:
        kind = msg.get_type()
        if kind == "BAD_DATA" or not self._for_us(msg):
            return
        if kind == "COMMAND_LONG":
            self._command(link, msg)
        elif kind == "SET_MODE":
            self._set_mode_custom(int(msg.custom_mode))
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._position_target(msg)
        elif kind == "PARAM_REQUEST_LIST":
            for i, name in enumerate(sorted(self.autopilot.params)):
                self._param_value(link, name, i)
        elif kind == "PARAM_REQUEST_READ":
            name = msg.param_id if msg.param_index < 0 else self._param_name(msg.param_index)
            if name in self.autopilot.params:
                self._param_value(link, name, sorted(self.autopilot.params).index(name))
        elif kind == "PARAM_SET":
            if msg.param_id in self.autopilot.params and math.isfinite(msg.param_value):
                self.autopilot.params[msg.param_id] = float(msg.param_value)
                self._param_value(link, msg.param_id, sorted(self.autopilot.params).index(msg.param_id))
        elif kind == "REQUEST_DATA_STREAM" and msg.start_stop and msg.req_message_rate > 0:
            # Legacy stream request (MAVProxy uses it with ArduPilot): everything at that rate.
            for mid in SUPPORTED_STREAMS:
                if not (mid == mavlink.MAVLINK_MSG_ID_ODOMETRY and self.options.flavour is Flavour.ARDUPILOT):
                    self.intervals_s[mid] = 1.0 / msg.req_message_rate

    def _param_name(self, index: int) -> str:
        names = sorted(self.autopilot.params)
        return names[index] if 0 <= index < len(names) else ""

    def _param_value(self, link: Any, name: str, index: int) -> None:
        link.mav.param_value_send(
            name.encode(),
            self.autopilot.params[name],
            mavlink.MAV_PARAM_TYPE_REAL32,
            len(self.autopilot.params),
            index,
        )

    def _position_target(self, msg: Any) -> None:
        ignore_position = mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
        if msg.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED or msg.type_mask & ignore_position:
            return  # only position targets in LOCAL_NED are honoured
        values = (msg.x, msg.y, msg.z, msg.yaw)
        if not all(math.isfinite(v) for v in values[:3]):
            return
        est = self._local(self.frame.odometry.pose)
        if msg.type_mask & mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE or not math.isfinite(msg.yaw):
            yaw = est.yaw_rad
        else:
            yaw = math.pi / 2.0 - msg.yaw
        height = -msg.z if not msg.type_mask & mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE else self.autopilot.height_m
        self.autopilot.position_target(self.sim.time_s, PositionTarget(Pose2(msg.y, msg.x, yaw), height))

    def _set_mode_custom(self, custom_mode: int) -> None:
        name = self.autopilot.mode_for_custom(custom_mode)
        if name is None:
            raise Refused(mavlink.MAV_RESULT_DENIED, f"unknown custom mode {custom_mode:#x}")
        self.autopilot.set_mode(name, self.sim.time_s, self._local(self.frame.odometry.pose))

    def _command(self, link: Any, msg: Any) -> None:
        cmd = int(msg.command)
        result = mavlink.MAV_RESULT_ACCEPTED
        ap = self.autopilot
        here = self._local(self.frame.odometry.pose)
        try:
            if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                if msg.param1 >= 0.5:
                    ap.arm(self.sim.time_s)
                else:
                    ap.disarm(force=abs(msg.param2 - 21196.0) < 0.5)
            elif cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
                ap.takeoff(self.sim.time_s, float(msg.param7), here)
            elif cmd == mavlink.MAV_CMD_NAV_LAND:
                ap.land(here)
            elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
                if self.options.flavour is Flavour.PX4:
                    custom = (int(msg.param2) << 16) | (int(msg.param3) << 24)
                else:
                    custom = int(msg.param2)
                self._set_mode_custom(custom)
            elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                result = self._set_interval(int(msg.param1), float(msg.param2))
            elif cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
                result = self._send_once(link, int(msg.param1))
            elif cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
                result = self._send_once(link, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
            else:
                result = mavlink.MAV_RESULT_UNSUPPORTED
        except Refused as refusal:
            result = refusal.result
            self._statustext(refusal.reason, mavlink.MAV_SEVERITY_WARNING)
        link.mav.command_ack_send(cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        for text in ap.messages:
            self._statustext(text)
        del ap.messages[:]

    def _set_interval(self, msg_id: int, interval_us: float) -> int:
        if msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY and self.options.flavour is Flavour.ARDUPILOT:
            return int(mavlink.MAV_RESULT_DENIED)  # ArduPilot does not send ODOMETRY
        if msg_id not in SUPPORTED_STREAMS:
            return int(mavlink.MAV_RESULT_DENIED)
        if interval_us < 0:
            self.intervals_s.pop(msg_id, None)
        elif interval_us == 0:
            default = PX4_DEFAULT_STREAMS.get(msg_id, 1.0)
            self.intervals_s[msg_id] = 1.0 / default
        else:
            self.intervals_s[msg_id] = interval_us / 1e6
        self._next_send.pop(msg_id, None)
        return int(mavlink.MAV_RESULT_ACCEPTED)

    def _send_once(self, link: Any, msg_id: int) -> int:
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._autopilot_version(link)
            return int(mavlink.MAV_RESULT_ACCEPTED)
        if msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY and self.options.flavour is Flavour.ARDUPILOT:
            return int(mavlink.MAV_RESULT_DENIED)
        if msg_id in SUPPORTED_STREAMS:
            self._send_stream(link, msg_id)
            return int(mavlink.MAV_RESULT_ACCEPTED)
        return int(mavlink.MAV_RESULT_DENIED)

    # -- sending --------------------------------------------------------------------------------

    def _statustext(self, text: str, severity: int | None = None) -> None:
        sev = mavlink.MAV_SEVERITY_INFO if severity is None else severity
        log.info("statustext: %s", text)
        for link in self.links:
            link.mav.statustext_send(sev, text.encode()[:50])

    def _send_due(self) -> None:
        now = self.sim.time_s
        if now >= self._next_heartbeat_s:
            self._next_heartbeat_s = now + 1.0
            for link in self.links:
                self._heartbeat(link)
        for msg_id, interval in list(self.intervals_s.items()):
            if now + 1e-9 >= self._next_send.get(msg_id, 0.0):
                self._next_send[msg_id] = max(self._next_send.get(msg_id, 0.0) + interval, now)
                for link in self.links:
                    self._send_stream(link, msg_id)

    def _heartbeat(self, link: Any) -> None:
        ap = self.autopilot
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
        if ap.mode in ("OFFBOARD", "GUIDED") or ap.mode.startswith("AUTO"):
            base |= mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        if ap.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        autopilot = (
            mavlink.MAV_AUTOPILOT_PX4 if self.options.flavour is Flavour.PX4 else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        )
        status = mavlink.MAV_STATE_ACTIVE if ap.armed else mavlink.MAV_STATE_STANDBY
        link.mav.heartbeat_send(mavlink.MAV_TYPE_QUADROTOR, autopilot, base, ap.custom_mode, status)

    def _boot_ms(self) -> int:
        return int(round(self.sim.time_s * 1000.0))

    def _send_stream(self, link: Any, msg_id: int) -> None:
        f = self.frame
        ap = self.autopilot
        local = self._local(f.odometry.pose)
        north, east, yaw_ned = core_to_ned(local.x_m, local.y_m, local.yaw_rad)
        ve, vn = f.odometry.velocity_xy or (0.0, 0.0)  # the estimator's, core axes (see sitl.drift)
        down = -ap.height_m
        usec = int(round(self.sim.time_s * 1e6))
        if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            link.mav.local_position_ned_send(self._boot_ms(), north, east, down, vn, ve, 0.0)
        elif msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            yaw_rate = -self.sim.vehicle.yaw_rate_rps
            link.mav.attitude_send(self._boot_ms(), 0.0, 0.0, yaw_ned, 0.0, 0.0, yaw_rate)
        elif msg_id == mavlink.MAVLINK_MSG_ID_ODOMETRY:
            c, s = math.cos(yaw_ned), math.sin(yaw_ned)
            vx_body, vy_body = c * vn + s * ve, -s * vn + c * ve  # ODOMETRY velocity in child frame
            nan_cov = [math.nan] + [0.0] * 20
            link.mav.odometry_send(
                usec,
                mavlink.MAV_FRAME_LOCAL_NED,
                mavlink.MAV_FRAME_BODY_FRD,
                north,
                east,
                down,
                quaternion_from_yaw(yaw_ned),
                vx_body,
                vy_body,
                0.0,
                0.0,
                0.0,
                -self.sim.vehicle.yaw_rate_rps,
                nan_cov,
                nan_cov,
                f.odometry.reset_counter,
                mavlink.MAV_ESTIMATOR_TYPE_VIO,
                100,
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE:
            od = encode_scan(f.scan, usec)
            link.mav.obstacle_distance_send(
                od.time_usec,
                mavlink.MAV_DISTANCE_SENSOR_INFRARED,
                list(od.distances_cm),
                0,
                od.min_distance_cm,
                od.max_distance_cm,
                od.increment_deg,
                od.angle_offset_deg,
                od.frame,
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            sensors = 0x3FFFFFFF & (mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO | mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL)
            health = sensors
            if self.options.flavour is Flavour.ARDUPILOT:
                # ArduPilot sets the geofence health bit whenever the fence is not breached, present
                # or not (ground stations such as MAVProxy announce "fence breach" without it).
                health |= mavlink.MAV_SYS_STATUS_GEOFENCE
            link.mav.sys_status_send(sensors, sensors, health, 200, 16000, -1, 90, 0, 0, 0, 0, 0, 0)
        elif msg_id == mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            if not ap.armed or ap.landed:
                landed = mavlink.MAV_LANDED_STATE_ON_GROUND
            elif ap.mode in ("AUTO.LAND", "LAND"):
                landed = mavlink.MAV_LANDED_STATE_LANDING
            elif ap.mode == "AUTO.TAKEOFF":
                landed = mavlink.MAV_LANDED_STATE_TAKEOFF
            else:
                landed = mavlink.MAV_LANDED_STATE_IN_AIR
            link.mav.extended_sys_state_send(mavlink.MAV_VTOL_STATE_UNDEFINED, landed)
        elif msg_id == mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat, lon = _offset_latlon(north, east)
            link.mav.global_position_int_send(
                self._boot_ms(),
                int(lat * 1e7),
                int(lon * 1e7),
                int((HOME_ALT_M + ap.height_m) * 1000),
                int(ap.height_m * 1000),
                int(vn * 100),
                int(ve * 100),
                0,
                int(math.degrees(yaw_ned) % 360.0 * 100),
            )
        elif msg_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            link.mav.home_position_send(
                int(HOME_LAT_DEG * 1e7),
                int(HOME_LON_DEG * 1e7),
                int(HOME_ALT_M * 1000),
                0.0,
                0.0,
                0.0,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                usec,
            )

    def _autopilot_version(self, link: Any) -> None:
        caps = (
            mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
            | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
            | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
            | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        )
        link.mav.autopilot_version_send(caps, 0, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, self.options.system_id)

    # -- the ground truth at the end ------------------------------------------------------------

    def report(self) -> dict[str, Any]:
        return {
            "map": self.world.name,
            "autopilot": self.options.flavour.value,
            "seed": self.options.seed,
            "coverage": round(self.coverage.coverage, 5),
            "sim_time_s": round(self.sim.time_s, 3),
            "path_length_m": round(self.sim.path_length_m, 3),
            "collisions": self.sim.collisions,
            "loop_closures_reported": len(self.loop_closures),
            "armed": self.autopilot.armed,
            "mode": self.autopilot.mode,
        }


def _offset_latlon(north_m: float, east_m: float) -> tuple[float, float]:
    lat = HOME_LAT_DEG + math.degrees(north_m / EARTH_RADIUS_M)
    lon = HOME_LON_DEG + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(HOME_LAT_DEG))))
    return lat, lon
