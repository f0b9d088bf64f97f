"""`sitl sensor`: only the simulated depth sensor and SLAM back end, following the pose of an
external MAVLink autopilot (a real PX4 or ArduPilot SITL, or `sitl run`), publishing on Zenoh.

The autopilot's local origin (where it booted) is placed at the map's start pose, with the local
frame's axes on the map's (x east, y north). The autopilot's own estimate is taken as the truth
the sensor scans from; the scans, odometry (that estimate, in the local frame) and loop closures
go out on the keys of :mod:`companion.links.zenoh_keys`.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import zenoh

from companion.core.geometry import Pose2
from companion.core.messages import Odometry
from companion.links.frames import ned_to_core
from companion.links.pymavlink_loader import load_mavutil
from companion.links.zenoh_codec import ENCODING, encode_loop_closure, encode_odometry, encode_scan
from companion.links.zenoh_keys import Keys
from sitl.depth_sensor import DepthSensor, SensorParams
from sitl.slam import SimulatedSlam, SlamParams
from sitl.world import World

log = logging.getLogger("sitl.sensor")
mavutil = load_mavutil()
mavlink: Any = mavutil.mavlink
SENSOR_COMPONENT_ID = 158  # MAV_COMP_ID_PERIPHERAL


class SensorNode:
    """Scans at the sensor rate from the autopilot's latest pose (paired with its heading)."""

    def __init__(self, world: World, url: str, session: Any, keys: Keys, seed: int = 1) -> None:
        self.world = world
        self.params = SensorParams()
        self.sensor = DepthSensor(world.walls, self.params, np.random.default_rng(seed))
        self.slam = SimulatedSlam(SlamParams(), world.walls)
        self.conn = mavutil.mavlink_connection(url, source_system=1, source_component=SENSOR_COMPONENT_ID)
        enc = zenoh.Encoding(ENCODING)
        self._pubs = {
            name: session.declare_publisher(key, encoding=enc)
            for name, key in (("scan", keys.scan), ("odometry", keys.odometry), ("loop_closure", keys.loop_closure))
        }
        self._yaw_ned: float | None = None
        self._local: Pose2 | None = None
        self._stamp_s = 0.0
        self._stop = False
        self.scans = 0

    def stop(self) -> None:
        self._stop = True

    def _map_pose(self, local: Pose2) -> Pose2:
        s = self.world.start
        return Pose2(local.x_m + s.x_m, local.y_m + s.y_m, local.yaw_rad)

    def run(self) -> None:
        if self.conn.wait_heartbeat(timeout=30) is None:
            raise TimeoutError("no autopilot heartbeat within 30 s")
        target = (self.conn.target_system, self.conn.target_component)
        for msg_id in (mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mavlink.MAVLINK_MSG_ID_ATTITUDE):
            self.conn.mav.command_long_send(
                *target, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 20_000, 0, 0, 0, 0, 0
            )
        period = 1.0 / self.params.rate_hz
        last_scan_stamp = -math.inf
        while not self._stop:
            msg = self.conn.recv_match(blocking=True, timeout=0.1)
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "ATTITUDE" and math.isfinite(msg.yaw):
                self._yaw_ned = float(msg.yaw)
            elif kind == "LOCAL_POSITION_NED" and self._yaw_ned is not None:
                stamp = msg.time_boot_ms / 1e3
                if not all(math.isfinite(v) for v in (msg.x, msg.y)):
                    continue
                local = ned_to_core(float(msg.x), float(msg.y), self._yaw_ned)
                velocity = (float(msg.vy), float(msg.vx))  # the autopilot's, in core axes (east, north)
                # Sensor rate in the autopilot's time, so a sped-up SITL gets scans as it should.
                if stamp - last_scan_stamp < period - 1e-3:
                    continue
                last_scan_stamp = stamp
                self._publish(stamp, local, velocity)

    def _publish(self, stamp_s: float, local: Pose2, velocity_xy: tuple[float, float] | None = None) -> None:
        pose = self._map_pose(local)
        finite = velocity_xy is not None and all(math.isfinite(v) for v in velocity_xy)
        self._pubs["odometry"].put(encode_odometry(Odometry(stamp_s, local, 0, velocity_xy if finite else None)))
        self._pubs["scan"].put(encode_scan(self.sensor.scan(pose, stamp_s)))
        closure = self.slam.observe(stamp_s, pose)
        if closure is not None:
            self._pubs["loop_closure"].put(encode_loop_closure(closure))
        self.scans += 1

    def close(self) -> None:
        for pub in self._pubs.values():
            pub.undeclare()
        self.conn.close()
