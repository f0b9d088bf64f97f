"""Edge conversions and the service's safety behaviour, without any network."""

from __future__ import annotations

import asyncio
import contextlib
import math
from pathlib import Path

import numpy as np
import pytest

from companion.config import check_mavlink_url, load_config
from companion.core.errors import ScanError
from companion.core.geometry import Pose2
from companion.core.messages import DepthScan, Odometry, Setpoint
from companion.errors import ConfigError
from companion.links.base import LinkError
from companion.links.frames import core_to_ned, ned_to_core, quaternion_from_yaw, yaw_from_quaternion
from companion.links.obstacle_distance import (
    MAV_FRAME_BODY_FRD,
    MAV_FRAME_LOCAL_NED,
    UINT16_MAX,
    ObstacleDistance,
    decode_scan,
    encode_scan,
)
from companion.service import MissionState, Service, ServiceSettings
from sitl.cli import main as sitl_main


def test_ned_and_core_frames_are_inverse_and_right_handed() -> None:
    # Facing north in NED (yaw 0) is facing +y in the core frame (yaw pi/2); east is +x.
    p = ned_to_core(2.0, 1.0, 0.0)
    assert (p.x_m, p.y_m) == (1.0, 2.0) and math.isclose(p.yaw_rad, math.pi / 2)
    for yaw in np.linspace(-3.0, 3.0, 13):
        n, e, y = core_to_ned(0.3, -0.7, float(yaw))
        back = ned_to_core(n, e, y)
        assert math.isclose(back.x_m, 0.3) and math.isclose(back.y_m, -0.7)
        assert math.isclose(math.cos(back.yaw_rad - yaw), 1.0, abs_tol=1e-12)
        assert math.isclose(yaw_from_quaternion(*quaternion_from_yaw(float(yaw))), float(yaw), abs_tol=1e-12)


def test_odometry_velocity_is_read_in_the_frame_its_child_frame_id_names() -> None:
    """ODOMETRY's velocity is in ``child_frame_id``'s frame (REP 147): PX4 sends the body's."""
    from companion.links.mavlink_link import mavlink, odometry_velocity_ned

    facing_east = math.pi / 2.0  # NED heading: clockwise from north
    north, east = odometry_velocity_ned(mavlink.MAV_FRAME_BODY_FRD, 1.0, 0.5, facing_east) or (0.0, 0.0)
    assert north == pytest.approx(-0.5) and east == pytest.approx(1.0)  # forward is east, right is south
    assert odometry_velocity_ned(mavlink.MAV_FRAME_LOCAL_NED, 1.0, 0.5, facing_east) == (1.0, 0.5)
    assert odometry_velocity_ned(mavlink.MAV_FRAME_BODY_FRD, math.nan, 0.0, 0.0) is None  # unknown
    assert odometry_velocity_ned(mavlink.MAV_FRAME_GLOBAL, 1.0, 0.0, 0.0) is None


def test_obstacle_distance_round_trip_keeps_bearings_and_ranges() -> None:
    bearings = np.linspace(-math.pi / 4, math.pi / 4, 64)
    ranges = 1.0 + np.arange(64) * 0.05
    ranges[5] = np.inf  # no return
    scan = DepthScan(1.5, bearings, ranges, 5.0, 0.1)
    msg = encode_scan(scan, 1_500_000)
    assert msg.frame == MAV_FRAME_BODY_FRD and len(msg.distances_cm) == 72
    assert msg.distances_cm[64:] == (UINT16_MAX,) * 8
    # First bin is the leftmost ray, at a negative (counter-clockwise) FRD angle.
    assert math.isclose(msg.angle_offset_deg, -45.0) and msg.distances_cm[0] == round(ranges[-1] * 100)
    back = decode_scan(msg, 1.5)
    np.testing.assert_allclose(back.bearings_rad, bearings, atol=1e-6)
    finite = np.isfinite(ranges)
    np.testing.assert_allclose(back.ranges_m[finite], ranges[finite], atol=0.006)
    assert np.isinf(back.ranges_m[5]) and back.ranges_m[5] > 0


def test_wide_scans_keep_the_nearest_return_per_bin() -> None:
    bearings = np.linspace(-1.0, 1.0, 144)
    ranges = np.full(144, 4.0)
    ranges[10] = 0.7
    msg = encode_scan(DepthScan(0.0, bearings, ranges, 5.0), 0)
    assert min(d for d in msg.distances_cm if d != UINT16_MAX) == 70
    assert sum(d != UINT16_MAX for d in msg.distances_cm) == 72


def test_north_aligned_obstacle_distance_needs_and_uses_the_heading() -> None:
    distances = (300,) * 8 + (UINT16_MAX,) * 64
    msg = ObstacleDistance(0, distances, 5.0, 80.0, 10, 500, MAV_FRAME_LOCAL_NED)
    with pytest.raises(ScanError, match="heading"):
        decode_scan(msg, 0.0)
    # Heading east (NED yaw 90 deg): a return at 90..125 deg from north is 0..35 deg to the right.
    scan = decode_scan(msg, 0.0, math.radians(90.0))
    assert math.isclose(float(scan.bearings_rad.min()), -math.radians(25.0), abs_tol=1e-9)
    assert math.isclose(float(scan.bearings_rad.max()), math.radians(10.0), abs_tol=1e-9)


def test_bad_obstacle_distance_is_refused() -> None:
    ok = (100,) * 72
    for bad in (
        ObstacleDistance(0, ok, 0.0, 0.0, 10, 500),
        ObstacleDistance(0, ok, math.nan, 0.0, 10, 500),
        ObstacleDistance(0, ok, 1.0, 0.0, 600, 500),
        ObstacleDistance(0, (UINT16_MAX,) * 72, 1.0, 0.0, 10, 500),
        ObstacleDistance(0, ok, 1.0, 0.0, 10, 500, frame=7),
    ):
        with pytest.raises(ScanError):
            decode_scan(bad, 0.0, 0.0)


def test_config_errors_name_the_file_and_the_problem(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("vehicle:\n  mavlink: udpin:127.0.0.1:1\n  setpoint_rate_hz: 1\n  altitud_m: 3\n")
    with pytest.raises(ConfigError) as err:
        load_config(bad)
    assert "bad.yaml" in str(err.value) and "setpoint_rate_hz" in str(err.value) and "altitud_m" in str(err.value)
    missing = tmp_path / "zenoh.yaml"
    missing.write_text("vehicle:\n  mavlink: udpin:127.0.0.1:1\ninputs:\n  scan: zenoh\n")
    with pytest.raises(ConfigError, match="no zenoh section"):
        load_config(missing)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "absent.yaml")


@pytest.mark.parametrize(
    ("url", "needle"),
    [
        ("udp://:14540", "MAVSDK-style"),  # MAVSDK's form: pymavlink took it for a serial device
        ("udpin:127.0.0.1:99999", "port 0-65535"),  # raised an OverflowError traceback at bind
        ("udpin:127.0.0.1:abc", "port 0-65535"),
        ("tcp:127.0.0.1:0", "port 1-65535"),  # nothing to connect to on port 0
        ("tcp:localhost", "tcp:HOST:PORT"),
        ("udpout::14550", "udpout:HOST:PORT"),
        (" ", "must name a connection"),
    ],
)
def test_a_bad_mavlink_url_is_a_config_error_before_any_socket_opens(tmp_path: Path, url: str, needle: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(f"vehicle:\n  mavlink: '{url}'\n")
    with pytest.raises(ConfigError, match=needle) as err:
        load_config(path)
    assert "vehicle.mavlink" in str(err.value)


@pytest.mark.parametrize(
    "url",
    ["udpin:0.0.0.0:14540", "udpin:0.0.0.0:0", "udp:127.0.0.1:14550", "tcp:127.0.0.1:5760", "/dev/ttyAMA0", "COM3"],
)
def test_pymavlink_urls_and_serial_devices_are_taken(url: str) -> None:
    assert check_mavlink_url(url) == url


def test_sitl_refuses_a_bad_mavlink_url_on_its_command_line(capsys: pytest.CaptureFixture[str]) -> None:
    """``sitl run --mavlink`` and ``sitl sensor --pose-from`` check URLs as the config does (an
    out-of-range port died in an OverflowError traceback at bind), and Zenoh endpoints and key
    chunks likewise."""
    for argv in (
        ["run", "--map", "config/maps/room.geojson", "--mavlink", "udpin:127.0.0.1:99999"],
        ["sensor", "--map", "config/maps/room.geojson", "--pose-from", "udp://:14540"],
        # and the Zenoh side (a ValueError traceback, or zenoh's Json5Err after the map loaded)
        ["run", "--map", "config/maps/room.geojson", "--vehicle-name", "drone 1"],
        ["sensor", "--map", "config/maps/room.geojson", "--pose-from", "udpin:127.0.0.1:1", "--zenoh-prefix", "a//b"],
        ["sensor", "--map", "config/maps/room.geojson", "--pose-from", "udpin:127.0.0.1:1", "--zenoh", "bogus"],
    ):
        with pytest.raises(SystemExit) as exit_info:
            sitl_main(argv)
        assert exit_info.value.code == 2
        assert argv[-2] in capsys.readouterr().err


@pytest.mark.parametrize(
    ("zenoh", "needle"),
    [
        ("connect: ['tcp/127.0.0.1:99999']", "port 1-65535"),  # zenoh opened, then waited for ever
        ("listen: ['127.0.0.1:7448']", "<protocol>/<address>"),
        ("connect: ['tcp/localhost']", "tcp/HOST:PORT"),
        ("prefix: 'fleet/**'", "key chunk '\\*\\*'"),  # a wildcard: no key to publish on
        ("vehicle: 'drone 1'", "key chunk 'drone 1'"),
    ],
)
def test_a_bad_zenoh_section_is_a_config_error_before_the_vehicle_is_waited_for(
    tmp_path: Path, zenoh: str, needle: str
) -> None:
    path = tmp_path / "z.yaml"
    path.write_text(f"vehicle:\n  mavlink: udpin:127.0.0.1:14540\ninputs:\n  scan: zenoh\nzenoh: {{{zenoh}}}\n")
    with pytest.raises(ConfigError, match=needle) as err:
        load_config(path)
    assert "z.yaml: zenoh" in str(err.value)
    listen_any = tmp_path / "ok.yaml"
    listen_any.write_text(
        "vehicle:\n  mavlink: udpin:127.0.0.1:14540\nzenoh: {listen: ['tcp/127.0.0.1:0'], prefix: a/b}\n"
    )
    assert load_config(listen_any).zenoh is not None


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["sim", "--seed", "-1"], "--seed"),  # numpy's seeding raised a ValueError traceback
        (["sim", "--seed", "1.5"], "--seed"),
        (["sim", "--noise-scale", "1e308"], "--noise-scale"),  # drifted to inf: shapely warnings, a dead run
        (["sim", "--max-time", "nan"], "--max-time"),
        (["sitl", "run", "--seed", "-1"], "--seed"),
        (["sitl", "run", "--noise-scale", "-1"], "--noise-scale"),  # was flown
        (["sitl", "run", "--noise-scale", "nan"], "--noise-scale"),  # was flown
        (["sitl", "run", "--ekf-delay", "-1"], "--ekf-delay"),
        (["sitl", "run", "--speedup", "0"], "--speedup"),
        (["sitl", "sensor", "--pose-from", "udpin:127.0.0.1:14550", "--seed", "-3"], "--seed"),
    ],
)
def test_bad_numbers_on_either_command_line_are_usage_errors(
    argv: list[str], option: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Both command lines check their numbers as they parse them: a usage error naming the option
    (exit 2) before any map is read or socket opened."""
    from companion.cli import main as companion_main

    run, args = (sitl_main, argv[1:]) if argv[0] == "sitl" else (companion_main, argv)
    with pytest.raises(SystemExit) as exit_info:
        run([*args[:1], "--map", "config/maps/room.geojson", *args[1:]])
    assert exit_info.value.code == 2
    assert f"argument {option}" in capsys.readouterr().err


def test_monitor_refuses_a_bad_key_expression_or_endpoint_before_opening_zenoh(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``companion monitor a//b`` (or ``--echo`` one) died in a zenoh.ZError traceback; now an
    error naming the rule (exit 2); a bad ``--connect`` is a usage error."""
    from companion.cli import main as companion_main

    for argv in (["monitor", "a//b", "--once"], ["monitor", "--echo", "x?y", "--once"]):
        assert companion_main([*argv, "--connect", "tcp/127.0.0.1:1"]) == 2
        err = " ".join(capsys.readouterr().err.split())
        assert "not a key expression" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exit_info:
        companion_main(["monitor", "--connect", "bogus", "--once"])
    assert exit_info.value.code == 2 and "argument --connect" in capsys.readouterr().err


def test_every_shipped_config_loads_and_keeps_zenoh_on_loopback() -> None:
    shipped = sorted(Path("config").glob("*.yaml"))
    assert len(shipped) >= 5  # sitl-px4, sitl-ardupilot, sitl-zenoh, firmware-px4, firmware-ardupilot
    for path in shipped:
        config = load_config(path)
        assert "127.0.0.1" in config.vehicle.mavlink, path
        if config.zenoh is not None:
            endpoints = [*config.zenoh.connect, *config.zenoh.listen]
            assert endpoints and all("127.0.0.1" in e for e in endpoints), path
            assert config.zenoh.multicast_scouting is False, path


class FakeVehicle:
    """Input source and flight control in one, recording what the service asked for."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.targets: list[Setpoint] = []
        self.handlers: tuple = ()  # type: ignore[type-arg]
        self.controlled = True

    def subscribe(self, on_odometry=None, on_scan=None, on_loop_closure=None) -> None:  # type: ignore[no-untyped-def]
        self.handlers = (on_odometry, on_scan)

    async def take_off(self, altitude_m: float, hold: Setpoint) -> None:
        self.calls.append("take_off")

    def set_target(self, setpoint: Setpoint) -> None:
        if not setpoint.is_finite():
            raise LinkError("non-finite")
        self.targets.append(setpoint)

    def in_control(self) -> bool:
        return self.controlled

    async def hold(self) -> None:
        self.calls.append("hold")

    async def land(self) -> None:
        self.calls.append("land")

    async def close(self) -> None:
        pass


def _scan(stamp: float) -> DepthScan:
    return DepthScan(stamp, np.linspace(-0.7, 0.7, 32), np.full(32, 3.0), 5.0)


def test_service_lands_when_scans_go_stale() -> None:
    async def scenario() -> tuple[Service, FakeVehicle, dict]:  # type: ignore[type-arg]
        fake = FakeVehicle()
        service = Service(ServiceSettings(input_timeout_s=0.3, startup_timeout_s=2.0), [fake], fake)
        task = asyncio.create_task(service.run())
        await asyncio.sleep(0)
        on_odom, on_scan = fake.handlers
        for i in range(10):  # inputs flow for a while, then the scans stop, odometry goes on
            on_odom(Odometry(i * 0.1, Pose2(0.0, 0.0, 0.0)))
            on_scan(_scan(i * 0.1))
            await asyncio.sleep(0.05)
        for i in range(10, 30):
            on_odom(Odometry(i * 0.1, Pose2(0.0, 0.0, 0.0)))
            await asyncio.sleep(0.05)
        return service, fake, await asyncio.wait_for(task, 5.0)

    service, fake, report = asyncio.run(scenario())
    assert fake.calls == ["take_off", "land"]
    assert fake.targets, "it flew before the scans stopped"
    assert report["termination"] == "error" and "scans stale" in report["reason"]
    assert service.health.state is MissionState.FAILED


def test_service_lands_on_a_bug_in_a_step_rather_than_leaving_the_vehicle_to_a_timeout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An exception the service does not expect (a bug, say shapely's ValueError from a view too
    small to be a polygon, as fuzzing found) used to end the mission task without a stop, leaving
    the vehicle to the autopilot's setpoint timeout. It stops the flight as any error does."""

    async def scenario() -> tuple[Service, FakeVehicle, dict]:  # type: ignore[type-arg]
        fake = FakeVehicle()
        service = Service(ServiceSettings(input_timeout_s=1.0, startup_timeout_s=2.0), [fake], fake)
        steps = 0
        real_step = service.explorer.step

        def step_then_fail(*args: object) -> object:
            nonlocal steps
            steps += 1
            if steps == 5:
                raise ValueError("A linearring requires at least 4 coordinates.")
            return real_step(*args)  # type: ignore[arg-type]

        monkeypatch.setattr(service.explorer, "step", step_then_fail)
        task = asyncio.create_task(service.run())
        await asyncio.sleep(0)
        on_odom, on_scan = fake.handlers
        for i in range(40):
            on_odom(Odometry(i * 0.1, Pose2(0.0, 0.0, 0.0)))
            on_scan(_scan(i * 0.1))
            await asyncio.sleep(0.03)
            if task.done():
                break
        return service, fake, await asyncio.wait_for(task, 5.0)

    service, fake, report = asyncio.run(scenario())
    assert fake.calls == ["take_off", "land"]
    assert report["termination"] == "error" and service.health.state is MissionState.FAILED
    assert "internal error" in service.health.reason and "linearring" in service.health.reason


def test_service_steps_a_scan_with_the_odometry_of_its_moment_even_when_that_comes_later() -> None:
    """The scan for t = 1 arrives before the odometry for t = 1 (as ArduPilot's pose, paired
    from two messages, does): the step waits for it, so the view is taken at once, not a scan
    later."""

    async def scenario() -> tuple[Service, int, int]:
        fake = FakeVehicle()
        # The wait ends when the odometry comes; its bound only has to outlast a loaded machine.
        settings = ServiceSettings(input_timeout_s=1.0, startup_timeout_s=2.0, scan_odometry_wait_s=2.0)
        service = Service(settings, [fake], fake)
        task = asyncio.create_task(service.run())
        await asyncio.sleep(0)
        on_odom, on_scan = fake.handlers
        on_odom(Odometry(0.0, Pose2(0.0, 0.0, 0.0)))
        on_scan(_scan(0.0))
        for _ in range(50):
            await asyncio.sleep(0.01)
            if service.step_ms:
                break
        steps = len(service.step_ms)
        on_odom(Odometry(0.9, Pose2(1.4, 0.0, 0.0)))
        on_scan(_scan(1.0))  # the first view is 1.5 m behind: a keyframe is due at t = 1
        await asyncio.sleep(0.01)
        on_scan(_scan(1.1))  # arrives while the step waits: it is the next step's
        await asyncio.sleep(0.01)
        on_odom(Odometry(1.0, Pose2(1.5, 0.0, 0.0)))
        for _ in range(50):
            await asyncio.sleep(0.01)
            if len(service.step_ms) > steps:
                break
        keyframes = len(service.explorer.map)
        on_odom(Odometry(1.1, Pose2(1.6, 0.0, 0.0)))
        for _ in range(50):
            await asyncio.sleep(0.01)
            if len(service.step_ms) > steps + 1:
                break
        steps = len(service.step_ms) - steps
        assert service.health.state is MissionState.EXPLORING, service.health.reason
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        return service, keyframes, steps

    service, keyframes, steps = asyncio.run(scenario())
    assert keyframes == 2
    assert service.explorer.map.keyframes[1].odom_pose == Pose2(1.5, 0.0, 0.0)
    assert steps == 2  # the scan that came during the wait was stepped too, and nothing failed
    assert service.health.scans_ahead_of_odometry == 0


def test_service_never_takes_off_without_inputs() -> None:
    async def scenario() -> tuple[FakeVehicle, dict]:  # type: ignore[type-arg]
        fake = FakeVehicle()
        service = Service(ServiceSettings(startup_timeout_s=0.3), [fake], fake)
        return fake, await service.run()

    fake, report = asyncio.run(scenario())
    assert fake.calls == []
    assert "no odometry and no scans" in report["reason"]


def test_odometry_with_an_attitude_quaternion_that_is_no_rotation_is_dropped() -> None:
    """ODOMETRY's ``q`` of all zeros (unset) read as heading north; a quaternion whose norm is
    far from 1 is dropped and counted like a non-finite pose, a unit one passes."""
    from types import SimpleNamespace

    from companion.links.mavlink_link import MavlinkLink, MavlinkSettings, mavlink

    link = MavlinkLink(MavlinkSettings("udpin:127.0.0.1:0"))
    got: list[Odometry] = []
    link.subscribe(on_odometry=got.append)

    def odometry(q: tuple[float, float, float, float]) -> SimpleNamespace:
        return SimpleNamespace(
            frame_id=mavlink.MAV_FRAME_LOCAL_NED,
            child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
            time_usec=1_000_000,
            x=1.0,
            y=2.0,
            z=-1.5,
            q=q,
            vx=0.0,
            vy=0.0,
            reset_counter=0,
        )

    link._odometry(odometry((0.0, 0.0, 0.0, 0.0)), 0.0)
    link._odometry(odometry((2.0, 0.0, 0.0, 0.0)), 0.0)
    assert got == [] and link.dropped == {"ODOMETRY": 2}
    link._odometry(odometry(quaternion_from_yaw(0.3)), 0.0)
    assert len(got) == 1 and got[0].pose.yaw_rad == pytest.approx(math.pi / 2 - 0.3)


def test_service_rejects_non_finite_odometry() -> None:
    fake = FakeVehicle()
    service = Service(ServiceSettings(), [fake], fake)
    service.on_odometry(Odometry(0.0, Pose2(math.nan, 0.0, 0.0)))
    assert service.health.rejected == {"odometry": 1} and service.health.odometry_count == 0


def test_commands_give_clear_errors_not_tracebacks(tmp_path: Path) -> None:
    import subprocess
    import sys

    bad = tmp_path / "bad.yaml"
    bad.write_text("vehicle: [1, 2]\n")
    for cmd in (
        ["companion.cli", "run", "--config", str(bad)],
        ["sitl.cli", "run", "--map", str(tmp_path / "missing.geojson")],
        ["sitl.cli", "sensor", "--map", str(tmp_path / "missing.geojson"), "--pose-from", "udpin:127.0.0.1:1"],
    ):
        run = subprocess.run([sys.executable, "-m", *cmd], capture_output=True, text=True, timeout=60)
        assert run.returncode == 2, run.stderr
        assert "Traceback" not in run.stderr + run.stdout
        assert ("bad.yaml" in run.stderr + run.stdout) or ("missing.geojson" in run.stderr)
    # A report path under a file: refused before the vehicle is waited for (the run ends in 2 s,
    # not after the 30 s heartbeat wait).
    good, blocker = tmp_path / "good.yaml", tmp_path / "a_file"
    good.write_text("vehicle:\n  mavlink: udpin:127.0.0.1:1\n")
    blocker.write_text("")
    cmd = ["companion.cli", "run", "--config", str(good), "--report", str(blocker / "r.json")]
    run = subprocess.run([sys.executable, "-m", *cmd], capture_output=True, text=True, timeout=20)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert str(blocker) in "".join((run.stderr + run.stdout).split())


def test_service_stops_when_the_vehicle_leaves_its_control() -> None:
    """A crash (disarmed) or a pilot taking over: stop at once, and do not fight them."""

    async def scenario() -> tuple[FakeVehicle, dict]:  # type: ignore[type-arg]
        fake = FakeVehicle()
        service = Service(ServiceSettings(input_timeout_s=1.0, startup_timeout_s=2.0), [fake], fake)
        task = asyncio.create_task(service.run())
        await asyncio.sleep(0)
        on_odom, on_scan = fake.handlers
        for i in range(20):
            if i == 10:
                fake.controlled = False
            on_odom(Odometry(i * 0.1, Pose2(0.0, 0.0, 0.0)))
            on_scan(_scan(i * 0.1))
            await asyncio.sleep(0.02)
        return fake, await asyncio.wait_for(task, 5.0)

    fake, report = asyncio.run(scenario())
    assert fake.calls == ["take_off"]
    assert report["termination"] == "error" and "left the companion's control" in report["reason"]
    assert 5 <= len(fake.targets) <= 11
