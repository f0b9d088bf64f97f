"""MAVLink end to end over UDP/TCP loopback: the ``sitl run`` vehicle as PX4 or ArduPilot, the
companion's link and service, and MAVSDK as a standard client."""

from __future__ import annotations

import asyncio
import json
import math
import socket
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from companion.core.messages import Setpoint
from companion.links.base import CommandRefused
from companion.links.mavlink_link import PX4_MAIN_OFFBOARD, MavlinkLink, MavlinkSettings
from sitl.autopilot import px4_custom_mode
from tests.sitl_process import ROOT, free_port, run_companion, sitl_vehicle

SPEEDUP = 10.0
# Whole explorations run slower: a millisecond of link latency is SPEEDUP times longer in vehicle
# time, and a late setpoint near a wall is what a real vehicle would never see.
EXPLORE_SPEEDUP = 5.0


def _link(url: str) -> MavlinkLink:
    # Setpoints at 10 Hz of simulated time, as 20 Hz would be on a real-time vehicle.
    return MavlinkLink(MavlinkSettings(url, setpoint_rate_hz=10.0 * SPEEDUP, connect_timeout_s=20.0))


async def _until(condition, timeout_s: float) -> bool:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        await asyncio.sleep(0.02)
    return bool(condition())


def test_px4_refuses_offboard_without_a_setpoint_stream(tmp_path: Path) -> None:
    async def scenario() -> None:
        with sitl_vehicle("px4", tmp_path / "sitl.json", SPEEDUP) as url:
            link = _link(url)
            await link.connect()
            try:
                with pytest.raises(CommandRefused) as refused:
                    await link._set_mode("OFFBOARD", PX4_MAIN_OFFBOARD)
                assert refused.value.result == "MAV_RESULT_TEMPORARILY_REJECTED"
                assert any("offboard" in r.lower() for r in refused.value.reasons)
                assert link.custom_mode != px4_custom_mode("OFFBOARD")
            finally:
                await link.close()

    asyncio.run(scenario())


def test_px4_falls_back_to_hold_when_the_companion_stops_streaming(tmp_path: Path) -> None:
    async def scenario() -> None:
        with sitl_vehicle("px4", tmp_path / "sitl.json", SPEEDUP) as url:
            link = _link(url)
            await link.connect()
            try:
                got_odometry: list[Setpoint] = []
                link.subscribe(on_odometry=lambda o: got_odometry.append(Setpoint(o.pose.x_m, o.pose.y_m, 0.0)))
                assert await _until(lambda: bool(got_odometry), 5.0)
                await link.take_off(1.5, Setpoint(got_odometry[-1].x_m, got_odometry[-1].y_m, 0.0))
                assert link.armed and link.custom_mode == px4_custom_mode("OFFBOARD")
                assert link.height_m > 1.2
                await link._stop_stream()
                # COM_OF_LOSS_T is 1 s of vehicle time; then COM_OBL_RC_ACT=0 without RC: Hold.
                assert await _until(lambda: link.custom_mode == px4_custom_mode("AUTO.LOITER"), 3.0)
                assert link.armed
            finally:
                await link.close()

    asyncio.run(scenario())


@pytest.mark.slow
@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_companion_run_explores_room_over_mavlink_with_zenoh_loop_closures(tmp_path: Path, autopilot: str) -> None:
    """Odometry and scans over MAVLink (ODOMETRY on PX4; LOCAL_POSITION_NED + ATTITUDE on
    ArduPilot, which has no ODOMETRY; OBSTACLE_DISTANCE), loop closures from the SLAM back end
    over Zenoh: full coverage. Over the wire room took 135-200 s of vehicle time in eight runs
    of session 13 (in-process 130-190 s); before scans waited for the odometry of their own
    stamp, the ArduPilot flavour took up to 550 s, so the limit stays generous at 900 s."""
    sitl_report = tmp_path / "sitl.json"
    report = tmp_path / "companion.json"
    zenoh_port = free_port(socket.SOCK_STREAM)
    extra = ("--zenoh", f"tcp/127.0.0.1:{zenoh_port}")
    with sitl_vehicle(autopilot, sitl_report, EXPLORE_SPEEDUP, extra=extra) as url:
        config = tmp_path / "config.yaml"
        config.write_text(
            f"vehicle:\n  mavlink: {url}\n  setpoint_rate_hz: {20 * EXPLORE_SPEEDUP}\n  arm_timeout_s: 30\n"
            "inputs:\n  odometry: mavlink\n  scan: mavlink\n  loop_closure: zenoh\n"
            f"zenoh:\n  connect: [tcp/127.0.0.1:{zenoh_port}]\n"
            "exploration:\n  max_time_s: 900\n"
        )
        run = run_companion(config, report, 300)
        assert report.exists(), run.stderr[-3000:]
        time.sleep(0.5)
    result = _explored(sitl_report, report, run, min_coverage=0.99)
    assert result["inputs"]["loop_closures"] > 10
    assert result["loop_closures"] > 10


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_shipped_config_flies_the_vehicle_over_mavlink_alone(tmp_path: Path, autopilot: str) -> None:
    """The shipped config (only the port, the sim-time setpoint rate and a 2 minute limit
    changed): ODOMETRY (PX4) or LOCAL_POSITION_NED + ATTITUDE (ArduPilot sends no ODOMETRY) and
    OBSTACLE_DISTANCE, no loop closures but those the companion finds by matching its own views.
    It explores, lands and exits by the report's termination.

    Whole explorations take 370-790 s of flight over the wire (four runs, all to coverage 0.9995
    or more, docs/interfaces.md): too long for the suite."""
    sitl_report = tmp_path / "sitl.json"
    report = tmp_path / "companion.json"
    shipped = yaml.safe_load((ROOT / f"config/sitl-{autopilot}.yaml").read_text())
    with sitl_vehicle(autopilot, sitl_report, EXPLORE_SPEEDUP) as url:
        shipped["vehicle"]["mavlink"] = url
        shipped["vehicle"]["setpoint_rate_hz"] = 20 * EXPLORE_SPEEDUP
        shipped["exploration"]["max_time_s"] = 120
        config = tmp_path / "config.yaml"
        config.write_text(yaml.safe_dump(shipped))
        run = run_companion(config, report, 180)
        assert report.exists(), run.stderr[-3000:]
        time.sleep(0.5)
    truth = json.loads(sitl_report.read_text())
    result = json.loads(report.read_text())
    normal_end = result["termination"] in ("complete", "unreachable_frontiers_left")
    assert result["termination"] == "timeout" or normal_end, result
    assert run.returncode == (0 if normal_end else 1), run.stderr[-3000:]
    assert result["inputs"]["loop_closures"] == 0  # none came over a link ...
    assert result["loop_closures"] == result["loop_closures_matched"]  # ... every one is the companion's
    assert result["keyframes"] > 20 and truth["path_length_m"] > 20.0
    assert truth["coverage"] > 0.5, (truth, result)
    assert truth["collisions"] == 0
    assert not truth["armed"], "the companion must leave the vehicle landed"


def _explored(sitl_report: Path, report: Path, run: subprocess.CompletedProcess[str], min_coverage: float) -> dict:  # type: ignore[type-arg]
    """The companion's report of a whole exploration that went well by the ground truth."""
    truth = json.loads(sitl_report.read_text())
    result = json.loads(report.read_text())
    assert run.returncode == 0, run.stderr[-3000:]
    assert result["termination"] in ("complete", "unreachable_frontiers_left")
    assert truth["collisions"] == 0
    assert truth["coverage"] >= min_coverage, (truth, result)
    assert not truth["armed"], "the companion must leave the vehicle landed"
    return result  # type: ignore[no-any-return]


def test_mavsdk_connects_arms_and_flies_an_offboard_setpoint(tmp_path: Path) -> None:
    from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
    from mavsdk.asyncio.plugins.action import ActionAsync
    from mavsdk.asyncio.plugins.offboard import OffboardAsync, PositionNedYaw
    from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

    port = free_port()

    async def scenario() -> None:
        config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        async with Mavsdk(config) as mavsdk:
            await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
            with sitl_vehicle("px4", tmp_path / "sitl.json", 2.0, extra=("--noise-scale", "0")):
                system = await mavsdk.first_autopilot(timeout_s=20.0)
                assert system is not None
                action, offboard, telemetry = ActionAsync(system), OffboardAsync(system), TelemetryAsync(system)
                target = PositionNedYaw(1.0, 0.5, -1.5, 45.0)
                await offboard.set_position_ned(target)
                await offboard.start()
                await action.arm()
                reached = False
                end = time.monotonic() + 20.0
                async for pv in telemetry.subscribe_position_velocity_ned():
                    p = pv.position
                    if math.hypot(p.north_m - 1.0, p.east_m - 0.5) < 0.2 and abs(p.down_m + 1.5) < 0.2:
                        reached = True
                        break
                    if time.monotonic() > end:
                        break
                assert reached
                await action.land()

    # sitl_vehicle picks its own port: point it at the one MAVSDK listens on instead.
    import tests.sitl_process as sp

    original = sp.free_port
    sp.free_port = lambda kind=None: port  # type: ignore[assignment,misc]
    try:
        asyncio.run(scenario())
    finally:
        sp.free_port = original


def test_companion_flies_through_the_mavsdk_backend(tmp_path: Path) -> None:
    """`control: mavsdk`: MAVSDK's Offboard plugin flies, pymavlink reads the inputs; the vehicle
    serves both endpoints, as PX4 serves its offboard and GCS ports."""
    mavsdk_port = free_port()
    speedup = 4.0  # MAVSDK streams setpoints at 20 Hz of wall time
    sitl_report, report = tmp_path / "sitl.json", tmp_path / "companion.json"
    extra = ("--mavlink", f"udpout:127.0.0.1:{mavsdk_port}")
    with sitl_vehicle("px4", sitl_report, speedup, extra=extra) as url:
        config = tmp_path / "config.yaml"
        config.write_text(
            f"vehicle:\n  mavlink: {url}\n  control: mavsdk\n  mavsdk_url: udpin://127.0.0.1:{mavsdk_port}\n"
            "exploration:\n  max_time_s: 25\n"
        )
        run = run_companion(config, report, 120)
        time.sleep(0.5)
    truth = json.loads(sitl_report.read_text())
    result = json.loads(report.read_text())
    assert result["termination"] == "timeout" and run.returncode == 1, run.stderr[-2000:]
    assert result["state"] == "done" and result["keyframes"] > 5
    assert truth["path_length_m"] > 10.0 and truth["coverage"] > 0.3
    assert truth["collisions"] == 0 and not truth["armed"] and truth["mode"] == "AUTO.LAND"
