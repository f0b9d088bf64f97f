"""The service's configuration: a YAML file validated by pydantic, with clear errors.

Every field has a safe default except where the vehicle is (the MAVLink URL). Unknown keys are
errors, so a typo never silently falls back to a default.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator

from companion.errors import ConfigError
from companion.links.zenoh_keys import Keys


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# pymavlink's connection kinds that take HOST:PORT, and whether port 0 is allowed (listening
# on any free port); uds:, unix:, ws:, wss:, wsserver: and mcast: are passed on unchecked.
_HOST_PORT_SCHEMES = {"udpin": True, "udp": True, "tcpin": True, "udpout": False, "udpbcast": False, "tcp": False}


def _is_host_port(address: str, lowest_port: int) -> bool:
    """``HOST:PORT`` with a host and a port from ``lowest_port`` to 65535 (MAVLink and Zenoh alike)."""
    host, sep, port = address.rpartition(":")
    return bool(sep and host and port.isdigit() and lowest_port <= int(port) <= 65535)


def check_mavlink_url(url: str) -> str:
    """A pymavlink connection string (``udpin:HOST:PORT``, ``tcp:HOST:PORT``, ... or a serial
    device), checked before any socket opens: a bad port raised an OverflowError traceback, and a
    MAVSDK-style ``udp://:14540`` was taken for a serial device and retried for 30 s."""
    if "://" in url:
        raise ValueError(
            f"{url!r} is a MAVSDK-style URL; pymavlink's are udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT "
            "or a serial device (MAVSDK's udp://:14540 is udpin:0.0.0.0:14540)"
        )
    scheme, sep, rest = url.partition(":")
    if sep and scheme in _HOST_PORT_SCHEMES:
        lowest = 0 if _HOST_PORT_SCHEMES[scheme] else 1
        if not _is_host_port(rest, lowest):
            raise ValueError(f"{url!r}: expected {scheme}:HOST:PORT with a port {lowest}-65535")
    elif not url.strip():
        raise ValueError("must name a connection (udpin:HOST:PORT, tcp:HOST:PORT, ...) or a serial device")
    return url


class VehicleConfig(_Strict):
    mavlink: str = Field(
        description="pymavlink URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a serial device"
    )
    baud: int = Field(921600, gt=0)
    control: Literal["pymavlink", "mavsdk"] = "pymavlink"
    mavsdk_url: str | None = Field(None, description="MAVSDK connection URL when control is mavsdk")
    setpoint_rate_hz: float = Field(20.0, gt=2.0, le=1000.0)
    max_setpoint_lead_m: float = Field(
        1.5, gt=0.2, le=10.0, description="setpoints stay this close to the vehicle: it bounds the autopilot's speed"
    )
    braking_accel_mps2: float = Field(
        1.0,
        gt=0.1,
        le=20.0,
        description="the horizontal acceleration the autopilot brakes and turns with at least (PX4 MPC_ACC_HOR, "
        "ArduPilot WPNAV_ACCEL): with a SLAM back end the setpoint lead keeps the way momentum carries the "
        "vehicle clear",
    )
    input_rate_hz: float = Field(10.0, gt=0.0, le=200.0)
    altitude_m: float = Field(1.5, gt=0.2, le=50.0)
    arm_timeout_s: float = Field(90.0, gt=0.0)
    command_timeout_s: float = Field(1.0, gt=0.0)

    @field_validator("mavlink")
    @classmethod
    def _mavlink_url(cls, url: str) -> str:
        return check_mavlink_url(url)


class InputsConfig(_Strict):
    odometry: Literal["mavlink", "zenoh"] = "mavlink"
    scan: Literal["mavlink", "zenoh"] = "mavlink"
    loop_closure: Literal["none", "zenoh", "scan_matching"] = Field(
        "none",
        description=(
            "where loop closures come from: none, a SLAM back end over zenoh, or scan_matching "
            "(the companion matches each new view to old ones itself; for drifting odometry "
            "without a back end, see docs/interfaces.md)"
        ),
    )


class SafetyConfig(_Strict):
    input_timeout_s: float = Field(1.0, gt=0.0, description="odometry or scans older than this stop the flight")
    startup_timeout_s: float = Field(60.0, gt=0.0, description="wait this long for the first inputs")
    on_stop: Literal["land", "hold"] = "land"


class ExplorationConfig(_Strict):
    max_time_s: float = Field(1800.0, gt=0.0, description="vehicle seconds of exploration before landing")
    odometry_drift_m_per_keyframe: float = Field(
        0.05,
        ge=0.0,
        le=1.0,
        description=(
            "how far the odometry may drift between keyframes (about a metre of flight): a view "
            "many keyframes away along the pose graph closes a frontier only this much deeper per "
            "keyframe. 0.05 suits odometry that drifts like the thesis's; an estimator with a "
            "global position (GPS, motion capture, an autopilot's own SITL) can use 0.005, and "
            "without loop closures must use a small value to finish (see docs/interfaces.md)"
        ),
    )
    odometry_drift_sigma_m_per_sqrt_m: float = Field(
        0.1,
        ge=0.0,
        le=2.0,
        description=(
            "how far the odometry drifts, one standard deviation per axis after a metre of flight "
            "(growing with the square root of the distance): the berth kept from remembered returns "
            "out of the sensor's view grows with it, as far as aligning them to new scans cannot "
            "fix (with a SLAM back end). 0.1 is the thesis's drift; at twice that drift with 0.1, a "
            "vehicle slid into a corner it had seen 2 s before (docs/benchmarks.md, session 57)"
        ),
    )
    max_scan_range_m: float = Field(
        20.0,
        gt=0.5,
        le=100.0,
        description=(
            "scans are taken to this range at most (farther returns count as none: a frontier at this "
            "range): a view's polygon, and a step's time, grow with the range (0.7 s a step at "
            "OBSTACLE_DISTANCE's 655 m). Most depth cameras reach 5-10 m, 2D lidars 10-40 m"
        ),
    )
    match_odometry_edges: bool | None = Field(
        None,
        description=(
            "correct each keyframe's odometry edge by matching its view's walls to the previous "
            "view's (companion.core.odometry_matching): the walls fix what they can, the odometry "
            "the rest (along a corridor). Unset: on with a SLAM back end (inputs.loop_closure: "
            "zenoh) or the companion's own loop closures (scan_matching), off with none, as "
            "measured (docs/benchmarks.md, sessions 27 and 62)"
        ),
    )


_IP_LOCATORS = ("tcp", "udp", "tls", "quic", "ws")  # Zenoh protocols whose address is HOST:PORT


def check_zenoh_endpoint(endpoint: str, listening: bool) -> str:
    """A Zenoh locator, ``<protocol>/<address>``; for the IP protocols HOST:PORT with a port in
    range (0, any free port, only to listen on). Zenoh opens a session with ``tcp/HOST:99999``
    to connect to and then waits for a peer that can never answer."""
    proto, sep, address = endpoint.partition("/")
    address = address.split("?", 1)[0].split("#", 1)[0]
    if not (sep and proto and address):
        raise ValueError(f"{endpoint!r}: expected <protocol>/<address>, e.g. tcp/127.0.0.1:7447")
    if proto in _IP_LOCATORS:
        lowest = 0 if listening else 1
        if not _is_host_port(address, lowest):
            raise ValueError(f"{endpoint!r}: expected {proto}/HOST:PORT with a port {lowest}-65535")
    return endpoint


class ZenohConfig(_Strict):
    prefix: str = "companion"
    vehicle: str = "sitl"
    connect: list[str] = Field(default_factory=list)
    listen: list[str] = Field(default_factory=list)
    mode: Literal["peer", "client", "router"] = "peer"
    multicast_scouting: bool = False
    overrides: dict[str, Any] = Field(default_factory=dict, description="other zenoh config paths, e.g. TLS")

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, endpoints: list[str], info: ValidationInfo) -> list[str]:
        return [check_zenoh_endpoint(e, info.field_name == "listen") for e in endpoints]

    @model_validator(mode="after")
    def _key_chunks(self) -> ZenohConfig:
        Keys(self.prefix, self.vehicle)  # a wildcard or empty chunk: a ValueError naming it
        return self


class Config(_Strict):
    vehicle: VehicleConfig
    inputs: InputsConfig = InputsConfig()
    safety: SafetyConfig = SafetyConfig()
    exploration: ExplorationConfig = ExplorationConfig()
    zenoh: ZenohConfig | None = None


def load_config(path: Path) -> Config:
    """Read and validate a config file; :class:`ConfigError` names the file and every problem."""
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror}") from None
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level")
    try:
        config = Config.model_validate(raw)
    except ValidationError as err:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in err.errors())
        raise ConfigError(f"{path}: {problems}") from None
    needs_zenoh = "zenoh" in (config.inputs.odometry, config.inputs.scan, config.inputs.loop_closure)
    if needs_zenoh and config.zenoh is None:
        raise ConfigError(f"{path}: inputs come from zenoh but there is no zenoh section")
    if config.vehicle.control == "mavsdk" and not config.vehicle.mavsdk_url:
        raise ConfigError(f"{path}: vehicle.control is mavsdk but vehicle.mavsdk_url is not set")
    return config
