"""The simulated depth camera and SLAM back end on Zenoh: full-resolution scans, odometry and
loop closures, on the keys of :mod:`companion.links.zenoh_keys`, as a real sensor node would."""

from __future__ import annotations

from typing import Any

import zenoh

from companion.core.geometry import Pose2
from companion.core.messages import Odometry
from companion.links.zenoh_codec import ENCODING, encode_loop_closure, encode_odometry, encode_scan
from companion.links.zenoh_keys import Keys
from sitl.simulation import SensorFrame


class ZenohSensorPublisher:
    """Publishes one simulation frame; odometry in the autopilot's local frame (origin at boot)."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        enc = zenoh.Encoding(ENCODING)
        self._scan: Any = session.declare_publisher(keys.scan, encoding=enc)
        self._odom: Any = session.declare_publisher(keys.odometry, encoding=enc)
        self._closure: Any = session.declare_publisher(keys.loop_closure, encoding=enc)
        self.published = 0

    def publish(self, frame: SensorFrame, local_pose: Pose2) -> None:
        odom = frame.odometry
        self._odom.put(encode_odometry(Odometry(frame.stamp_s, local_pose, odom.reset_counter, odom.velocity_xy)))
        self._scan.put(encode_scan(frame.scan))
        if frame.loop_closure is not None:
            self._closure.put(encode_loop_closure(frame.loop_closure))
        self.published += 1

    def close(self) -> None:
        for pub in (self._scan, self._odom, self._closure):
            pub.undeclare()
