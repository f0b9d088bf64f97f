"""Zenoh: payload validation, and two processes over loopback TCP (multicast scouting off): the
sitl publishes sensors, the companion explores with them, a monitor watches, garbage is dropped."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.core.geometry import Pose2
from companion.core.messages import DepthScan, LoopClosure, Odometry
from companion.links.zenoh_codec import (
    MAX_PAYLOAD_BYTES,
    PayloadError,
    decode_loop_closure,
    decode_odometry,
    decode_scan,
    encode_loop_closure,
    encode_odometry,
    encode_scan,
)
from companion.links.zenoh_keys import Keys
from companion.links.zenoh_link import ZenohSettings, open_session
from companion.monitor import Monitor
from sitl.depth_sensor import SensorParams
from tests.sitl_process import ROOT, free_port, run_companion, running, sitl_vehicle


def test_payloads_round_trip() -> None:
    b = np.linspace(-0.7, 0.7, 300)
    r = np.where(np.arange(300) % 7 == 0, np.inf, 1.0 + np.arange(300) / 100.0)
    scan = decode_scan(encode_scan(DepthScan(12.5, b, r, 5.0, 0.1)))
    assert scan.stamp_s == 12.5 and scan.bearings_rad.size == 300
    np.testing.assert_allclose(scan.bearings_rad, b, atol=1e-9)
    assert np.array_equal(np.isinf(scan.ranges_m), np.isinf(r) | (r >= 5.0))
    odom = decode_odometry(encode_odometry(Odometry(3.0, Pose2(1.0, -2.0, 0.5), 2)))
    assert odom == Odometry(3.0, Pose2(1.0, -2.0, 0.5), 2) and odom.velocity_xy is None
    moving = Odometry(3.0, Pose2(1.0, -2.0, 0.5), 2, (0.75, -0.25))
    assert decode_odometry(encode_odometry(moving)) == moving
    closure = LoopClosure(1.0, 9.0, Pose2(0.1, 0.2, -0.3))
    assert decode_loop_closure(encode_loop_closure(closure)) == closure


@pytest.mark.parametrize(
    ("payload", "kind"),
    [
        (b"{not json", "malformed"),
        (b'{"schema": 1, "type": "odometry", "stamp_s": 1.0, "pose": {"x_m": 1', "malformed"),  # truncated
        (b'{"schema": 2, "type": "odometry"}', "schema"),
        (b'{"schema": 1, "type": "scan"}', "type"),
        (
            b'{"schema": 1, "type": "odometry", "stamp_s": 1.0, "pose": {"x_m": NaN, "y_m": 0, "yaw_rad": 0}}',
            "malformed",
        ),
        (
            b'{"schema": 1, "type": "odometry", "stamp_s": 1e999, "pose": {"x_m": 0, "y_m": 0, "yaw_rad": 0}}',
            "non_finite",
        ),
        (b'{"schema": 1, "type": "odometry", "stamp_s": 1.0}', "missing"),
        (
            b'{"schema": 1, "type": "odometry", "stamp_s": 1.0, "pose": {"x_m": 0, "y_m": 0, "yaw_rad": 0},'
            b' "velocity": [1.0, 0.0]}',
            "missing",
        ),
        (
            b'{"schema": 1, "type": "odometry", "stamp_s": 1.0, "pose": {"x_m": 0, "y_m": 0, "yaw_rad": 0},'
            b' "velocity": {"x_mps": 1e999, "y_mps": 0}}',
            "non_finite",
        ),
        (b" " * (MAX_PAYLOAD_BYTES + 1), "oversized"),
        # JSON integers have no bound: one of 400 digits raised an OverflowError out of the decoder
        (
            b'{"schema": 1, "type": "odometry", "stamp_s": 1'
            + b"0" * 400
            + b', "pose": {"x_m": 0, "y_m": 0, "yaw_rad": 0}}',
            "non_finite",
        ),
    ],
)
def test_bad_odometry_payloads_are_rejected_by_kind(payload: bytes, kind: str) -> None:
    with pytest.raises(PayloadError) as err:
        decode_odometry(payload)
    assert err.value.kind == kind


def test_bad_scans_are_rejected() -> None:
    good = json.loads(encode_scan(DepthScan(1.0, np.linspace(-0.5, 0.5, 10), np.ones(10), 5.0)))
    for change, kind in (
        ({"ranges_m": [1.0]}, "truncated"),
        ({"ranges_m": ["a"] * 10}, "malformed"),
        ({"angle_increment_rad": -0.1}, "malformed"),
        ({"angle_increment_rad": 1.0}, "invalid_scan"),  # 10 rays x 1 rad: more than a full turn
        ({"ranges_m": [10**400] * 10}, "non_finite"),  # an OverflowError before
        ({"angle_min_rad": -(10**400)}, "non_finite"),
    ):
        with pytest.raises(PayloadError) as err:
            decode_scan(json.dumps({**good, **change}).encode())
        assert err.value.kind == kind


def test_keys_come_from_one_prefix_and_name() -> None:
    keys = Keys("fleet/a", "uav1")
    assert keys.scan == "fleet/a/uav1/sensors/scan"
    assert keys.keyframe(7) == "fleet/a/uav1/companion/map/keyframes/7"
    with pytest.raises(ValueError):
        Keys("bad*", "x")


@pytest.mark.slow
def test_companion_explores_room_with_zenoh_sensors_monitored_and_garbage_dropped(tmp_path: Path) -> None:
    sitl_port, companion_port = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_STREAM)
    sitl_ep, companion_ep = f"tcp/127.0.0.1:{sitl_port}", f"tcp/127.0.0.1:{companion_port}"
    speedup = 5.0  # see EXPLORE_SPEEDUP in test_mavlink_sitl.py
    report, sitl_report = tmp_path / "companion.json", tmp_path / "sitl.json"
    with sitl_vehicle("px4", sitl_report, speedup, extra=("--zenoh", sitl_ep)) as url:
        config = tmp_path / "config.yaml"
        config.write_text(
            f"vehicle:\n  mavlink: {url}\n  setpoint_rate_hz: {20 * speedup}\n"
            "inputs:\n  odometry: zenoh\n  scan: zenoh\n  loop_closure: zenoh\n"
            f"zenoh:\n  connect: ['{sitl_ep}']\n  listen: ['{companion_ep}']\n"
            "exploration:\n  max_time_s: 600\n"
        )
        cmd = ["companion.cli", "run", "--config", str(config), "--report", str(report)]
        with running(cmd, "companion") as companion:
            keys = Keys()
            monitor = Monitor()
            session = open_session(ZenohSettings(connect=(sitl_ep, companion_ep)))
            try:
                sub = session.declare_subscriber(
                    keys.everything, lambda s: monitor.on_sample(str(s.key_expr), s.payload.to_bytes())
                )
                time.sleep(5.0)
                # Garbage on the input keys while the companion explores.
                for i in range(30):
                    session.put(keys.scan, b'{"schema": 1, "type": "scan", "ranges_m": [1')
                    session.put(keys.odometry, b'{"schema": 1, "type": "odometry", "stamp_s": 1e999}')
                    session.put(keys.loop_closure, b"\xff\xfe" * (i + 1))
                    time.sleep(0.01)
                time.sleep(3.0)
                now = time.monotonic()
                stats = dict(monitor.stats)
                rates = {k: s.rate_hz(now) for k, s in stats.items()}
                reply = list(session.get(keys.map, timeout=5.0))
                sub.undeclare()
            finally:
                session.close()
            companion.wait(240)
        assert companion.returncode == 0, report.read_text()
    result = json.loads(report.read_text())
    truth = json.loads(sitl_report.read_text())
    assert truth["coverage"] >= 0.99 and truth["collisions"] == 0 and not truth["armed"]
    assert result["termination"] in ("complete", "unreachable_frontiers_left")
    # With a back end's loop closures the keyframes' odometry edges are matched too.
    assert 0 < result["odometry_edges_matched"] < result["keyframes"]
    # Scans all the way through (the sensor's 10 Hz of simulated time; a little lost at start and end)
    expected_scans = truth["sim_time_s"] * SensorParams().rate_hz
    assert result["inputs"]["scans"] >= 0.8 * expected_scans and result["inputs"]["loop_closures"] > 10
    rejected = result["inputs"]["rejected"]
    assert rejected.get("scan:malformed", 0) == 30
    assert rejected.get("odometry:non_finite", 0) == 30
    assert rejected.get("loop_closure:malformed", 0) == 30
    # The monitor saw sensors at the sensor rate (10 Hz of vehicle time, sped up) and the companion's
    # keys: a setpoint per step, state and health about once per second.
    sensor_hz = 10.0 * speedup  # 10 Hz of vehicle time
    # Never faster than the sensor; slower only when this busy machine cannot keep the speed-up.
    assert 0.5 * sensor_hz < rates[keys.scan] < 1.2 * sensor_hz
    assert rates[keys.setpoint] > 0.3 * sensor_hz
    assert 0.5 <= rates[keys.state] <= 5.0 and 0.5 <= rates[keys.health] <= 5.0
    assert any(k.startswith(f"{keys.root}/companion/map/keyframes/") for k in stats)
    assert reply and reply[0].ok is not None
    body = json.loads(reply[0].ok.payload.to_bytes())
    assert body["type"] == "map" and len(body["keyframes"]) > 5
    assert all(len(kf["vertices_xy"]) == len(kf["kinds"]) for kf in body["keyframes"])


def test_monitor_says_when_nothing_is_reachable() -> None:
    port = free_port(socket.SOCK_STREAM)
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "companion.cli",
            "monitor",
            "--once",
            "--duration",
            "1",
            "--connect",
            f"tcp/127.0.0.1:{port}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert run.returncode == 1
    assert "nothing reachable" in run.stdout


@pytest.mark.slow
def test_sitl_sensor_follows_an_external_autopilot_and_the_companion_explores(tmp_path: Path) -> None:
    """The real-firmware set-up: an autopilot flies (here `sitl run` without sensors on the bus),
    `sitl sensor` follows its pose and publishes scans on Zenoh, the companion explores."""
    sensor_port, zenoh_port = free_port(), free_port(socket.SOCK_STREAM)
    zenoh_ep = f"tcp/127.0.0.1:{zenoh_port}"
    speedup = 5.0  # see EXPLORE_SPEEDUP in test_mavlink_sitl.py
    report, sitl_report = tmp_path / "companion.json", tmp_path / "sitl.json"
    extra = ("--mavlink", f"udpout:127.0.0.1:{sensor_port}", "--noise-scale", "0")
    with sitl_vehicle("px4", sitl_report, speedup, extra=extra) as url:
        sensor_cmd = ["sitl.cli", "sensor", "--map", str(ROOT / "config/maps/room.geojson")]
        sensor_cmd += ["--pose-from", f"udpin:127.0.0.1:{sensor_port}", "--zenoh", zenoh_ep]
        with running(sensor_cmd, "sitl-sensor"):
            config = tmp_path / "config.yaml"
            config.write_text(
                f"vehicle:\n  mavlink: {url}\n  setpoint_rate_hz: {20 * speedup}\n"
                "inputs:\n  odometry: zenoh\n  scan: zenoh\n  loop_closure: zenoh\n"
                f"zenoh:\n  connect: ['{zenoh_ep}']\n"
                "exploration:\n  max_time_s: 600\n"
            )
            run = run_companion(config, report, 240)
        time.sleep(0.5)
    assert run.returncode == 0, run.stderr[-3000:]
    truth = json.loads(sitl_report.read_text())
    result = json.loads(report.read_text())
    assert truth["coverage"] >= 0.99 and truth["collisions"] == 0 and not truth["armed"]
    # Scans all the way through (the sensor's 10 Hz of simulated time; a little lost at start and end)
    expected_scans = truth["sim_time_s"] * SensorParams().rate_hz
    assert result["inputs"]["scans"] >= 0.8 * expected_scans and result["inputs"]["loop_closures"] > 10
