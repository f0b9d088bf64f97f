"""JSON payloads on Zenoh: encode with a schema version, decode with validation.

A payload that is malformed, truncated, oversized, of another schema version or holds a
non-finite number raises :class:`PayloadError`; the link counts and drops it, so it never reaches
the map. Units are SI (metres, radians, seconds); frames are the core's (x forward at start, y left,
yaw counter-clockwise; scan bearings counter-clockwise from forward).
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from companion.core.errors import ScanError
from companion.core.geometry import Pose2
from companion.core.messages import DepthScan, LoopClosure, Odometry

SCHEMA_VERSION = 1
ENCODING = "application/json"
MAX_PAYLOAD_BYTES = 1 << 20  # 1 MiB: a 4096-point scan is about 100 kB


class PayloadError(ValueError):
    """A payload that cannot be decoded into a valid message; ``kind`` names the problem."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind


def dumps(kind: str, body: dict[str, Any]) -> bytes:
    return json.dumps({"schema": SCHEMA_VERSION, "type": kind, **body}, allow_nan=False, separators=(",", ":")).encode()


def _reject_constant(name: str) -> float:
    """JSON has no NaN or Infinity; Python's parser accepts them unless told not to."""
    raise ValueError(f"{name} is not JSON")


def _load(payload: bytes, kind: str) -> dict[str, Any]:
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise PayloadError("oversized", f"{len(payload)} bytes > {MAX_PAYLOAD_BYTES}")
    try:
        data = json.loads(payload, parse_constant=_reject_constant)
    except (ValueError, UnicodeDecodeError) as err:
        raise PayloadError("malformed", str(err)[:80]) from None
    if not isinstance(data, dict):
        raise PayloadError("malformed", "not a JSON object")
    if data.get("schema") != SCHEMA_VERSION:
        raise PayloadError("schema", f"schema {data.get('schema')!r}, expected {SCHEMA_VERSION}")
    if data.get("type") != kind:
        raise PayloadError("type", f"type {data.get('type')!r}, expected {kind!r}")
    return data


def _number(data: dict[str, Any], name: str) -> float:
    value = data.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise PayloadError("missing", f"{name} must be a number")
    number = _finite_float(value)
    if number is None:
        raise PayloadError("non_finite", f"{name} is not finite")
    return number


def _finite_float(value: float) -> float | None:
    """``value`` as a finite float, or None: JSON integers have no bound, and one of 400 digits
    raised an OverflowError (not a PayloadError) out of the decoder."""
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _pose(data: dict[str, Any], name: str) -> Pose2:
    p = data.get(name)
    if not isinstance(p, dict):
        raise PayloadError("missing", f"{name} must be an object with x_m, y_m, yaw_rad")
    return Pose2(_number(p, "x_m"), _number(p, "y_m"), _number(p, "yaw_rad"))


def _pose_body(pose: Pose2) -> dict[str, float]:
    return {"x_m": pose.x_m, "y_m": pose.y_m, "yaw_rad": pose.yaw_rad}


# -- odometry ---------------------------------------------------------------------------------


def encode_odometry(odom: Odometry) -> bytes:
    """The pose, and the estimator's velocity when it has one (``velocity``: x_mps, y_mps)."""
    body: dict[str, Any] = {"stamp_s": odom.stamp_s, "pose": _pose_body(odom.pose), "reset_counter": odom.reset_counter}
    if odom.velocity_xy is not None:
        body["velocity"] = {"x_mps": odom.velocity_xy[0], "y_mps": odom.velocity_xy[1]}
    return dumps("odometry", body)


def decode_odometry(payload: bytes) -> Odometry:
    d = _load(payload, "odometry")
    reset = d.get("reset_counter", 0)
    if not isinstance(reset, int) or isinstance(reset, bool) or reset < 0:
        raise PayloadError("missing", "reset_counter must be a non-negative integer")
    velocity = None
    if d.get("velocity") is not None:
        v = d["velocity"]
        if not isinstance(v, dict):
            raise PayloadError("missing", "velocity must be an object with x_mps, y_mps")
        velocity = (_number(v, "x_mps"), _number(v, "y_mps"))
    return Odometry(_number(d, "stamp_s"), _pose(d, "pose"), reset, velocity)


# -- scans ------------------------------------------------------------------------------------


def encode_scan(scan: DepthScan) -> bytes:
    """Ranges as numbers, with ``null`` for no return (REP 117 +inf) and for invalid readings."""
    r = scan.ranges_m
    ranges: list[float | None] = [None if not math.isfinite(v) or v >= scan.max_range_m else float(v) for v in r]
    return dumps(
        "scan",
        {
            "stamp_s": scan.stamp_s,
            "angle_min_rad": float(scan.bearings_rad[0]),
            "angle_increment_rad": float((scan.bearings_rad[-1] - scan.bearings_rad[0]) / (r.size - 1)),
            "range_min_m": scan.min_range_m,
            "range_max_m": scan.max_range_m,
            "ranges_m": ranges,
        },
    )


def decode_scan(payload: bytes) -> DepthScan:
    d = _load(payload, "scan")
    ranges = d.get("ranges_m")
    if not isinstance(ranges, list) or len(ranges) < 2:
        raise PayloadError("truncated", "ranges_m must be a list of at least two entries")
    if any(v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))) for v in ranges):
        raise PayloadError("malformed", "ranges_m entries must be numbers or null")
    increment = _number(d, "angle_increment_rad")
    if increment <= 0.0:
        raise PayloadError("malformed", "angle_increment_rad must be positive")
    try:
        r = np.array([math.inf if v is None else float(v) for v in ranges])
    except OverflowError:
        raise PayloadError("non_finite", "ranges_m holds a number too large for a float") from None
    if np.isnan(r).any():
        raise PayloadError("non_finite", "ranges_m holds NaN")
    bearings = (_number(d, "angle_min_rad") + increment * np.arange(r.size)).astype(np.float64)
    try:
        return DepthScan(_number(d, "stamp_s"), bearings, r, _number(d, "range_max_m"), _number(d, "range_min_m"))
    except ScanError as err:
        raise PayloadError("invalid_scan", str(err)) from None


# -- loop closures ----------------------------------------------------------------------------


def encode_loop_closure(closure: LoopClosure) -> bytes:
    return dumps(
        "loop_closure",
        {
            "earlier_stamp_s": closure.earlier_stamp_s,
            "current_stamp_s": closure.current_stamp_s,
            "earlier_to_current": _pose_body(closure.earlier_to_current),
        },
    )


def decode_loop_closure(payload: bytes) -> LoopClosure:
    d = _load(payload, "loop_closure")
    earlier, current = _number(d, "earlier_stamp_s"), _number(d, "current_stamp_s")
    if earlier >= current:
        raise PayloadError("malformed", "earlier_stamp_s must precede current_stamp_s")
    return LoopClosure(earlier, current, _pose(d, "earlier_to_current"))
