"""The MAVLink link over a serial port (a pseudo-terminal standing in for the flight controller's
UART): pymavlink opens serial devices through pyserial, which must be installed for it."""

from __future__ import annotations

import asyncio
import os
import select
import threading
import tty

from companion.links.mavlink_link import COMPANION_COMPONENT_ID, MavlinkLink, MavlinkSettings
from companion.links.pymavlink_loader import load_mavutil

mavutil = load_mavutil()
mavlink = mavutil.mavlink


class _SerialAutopilot(threading.Thread):
    """A minimal PX4 on the master side of a pty: heartbeats at 10 Hz, every command ACKed."""

    def __init__(self, master_fd: int) -> None:
        super().__init__(daemon=True)
        self.fd = master_fd
        self.stop = threading.Event()
        self.mav = mavlink.MAVLink(self, srcSystem=1, srcComponent=1)
        self.heard: list[tuple[int, str, int]] = []  # (source component, message, detail)

    def write(self, data: bytes) -> None:
        os.write(self.fd, data)

    def run(self) -> None:
        while not self.stop.is_set():
            self.mav.heartbeat_send(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, mavlink.MAV_STATE_STANDBY
            )
            ready, _, _ = select.select([self.fd], [], [], 0.1)
            if not ready:
                continue
            for msg in self.mav.parse_buffer(os.read(self.fd, 4096)) or []:
                comp = msg.get_srcComponent()
                if msg.get_type() == "HEARTBEAT":
                    self.heard.append((comp, "HEARTBEAT", msg.type))
                elif msg.get_type() == "COMMAND_LONG":
                    self.heard.append((comp, "COMMAND_LONG", int(msg.param1)))
                    self.mav.command_ack_send(msg.command, mavlink.MAV_RESULT_ACCEPTED)


def test_the_link_connects_over_a_serial_port_as_the_onboard_computer() -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    autopilot = _SerialAutopilot(master)
    autopilot.start()
    link = MavlinkLink(MavlinkSettings(url=os.ttyname(slave), baud=57600, connect_timeout_s=10.0))

    async def session() -> None:
        await link.connect()
        await link.close()

    try:
        asyncio.run(asyncio.wait_for(session(), 20.0))
    finally:
        autopilot.stop.set()
        autopilot.join(2.0)
        os.close(slave)
        os.close(master)
    assert link.autopilot == "px4" and link.target_system == 1
    heard = autopilot.heard
    assert (COMPANION_COMPONENT_ID, "HEARTBEAT", mavlink.MAV_TYPE_ONBOARD_CONTROLLER) in heard
    # The streams it needs were asked for over the same wire (ODOMETRY first on PX4).
    asked = [detail for comp, name, detail in heard if comp == COMPANION_COMPONENT_ID and name == "COMMAND_LONG"]
    assert mavlink.MAVLINK_MSG_ID_ODOMETRY in asked and mavlink.MAVLINK_MSG_ID_OBSTACLE_DISTANCE in asked
