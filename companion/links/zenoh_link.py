"""The Zenoh link: one session config, inputs (scans, odometry, loop closures) and the companion's
outputs (state, health, setpoint, map keyframes, frontiers, a liveliness token and a map queryable).

Zenoh calls handlers on its own threads; inputs are handed to the asyncio loop with
``call_soon_threadsafe``. Bad payloads are counted per kind, logged once per kind, and dropped.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh

from companion.core.local_map import LocalMap
from companion.core.messages import Setpoint
from companion.links.base import LinkError, LoopClosureHandler, OdometryHandler, ScanHandler
from companion.links.zenoh_codec import (
    ENCODING,
    PayloadError,
    decode_loop_closure,
    decode_odometry,
    decode_scan,
    dumps,
)
from companion.links.zenoh_keys import Keys

log = logging.getLogger("companion.zenoh")


@dataclass(frozen=True, slots=True)
class ZenohSettings:
    """How to join the bus. Defaults are loopback-safe: no multicast scouting, no gossip."""

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    multicast_scouting: bool = False
    overrides: dict[str, Any] = field(default_factory=dict)  # any other zenoh config path -> value


def session_config(settings: ZenohSettings) -> zenoh.Config:
    """The one place a Zenoh session is configured (deployments add router endpoints, TLS, ...)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(settings.mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    conf.insert_json5("scouting/gossip/enabled", "false")
    for path, value in settings.overrides.items():
        conf.insert_json5(path, json.dumps(value))
    return conf


def check_key_expr(text: str) -> str:
    """A key expression Zenoh accepts (for subscribing: wildcards allowed), or a LinkError saying
    why not, before any session opens."""
    try:
        zenoh.KeyExpr(text)
    except Exception as err:  # zenoh raises its own ZError
        reason = str(err).split(" at /", 1)[0]  # without the Rust source location
        raise LinkError(f"not a key expression: {reason}") from None
    return text


def open_session(settings: ZenohSettings) -> zenoh.Session:
    try:
        return zenoh.open(session_config(settings))
    except Exception as err:  # zenoh raises its own ZError
        raise LinkError(
            f"cannot open a Zenoh session ({settings.mode}, connect {list(settings.connect)}): {err}"
        ) from None


class DropCounter:
    """Counts rejected payloads per kind; logs the first of each kind."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def drop(self, stream: str, err: PayloadError) -> None:
        key = f"{stream}:{err.kind}"
        with self._lock:
            first = key not in self.counts
            self.counts[key] = self.counts.get(key, 0) + 1
        if first:
            log.warning("dropping bad %s payload: %s (logged once per kind; counted)", stream, err)


class ZenohInputs:
    """Scans, odometry and loop closures from Zenoh, for the streams the config takes from it."""

    def __init__(self, session: zenoh.Session, keys: Keys, streams: set[str]) -> None:
        self._session = session
        self._keys = keys
        self._streams = streams
        self._subscribers: list[Any] = []
        self.drops = DropCounter()

    def subscribe(
        self,
        on_odometry: OdometryHandler | None = None,
        on_scan: ScanHandler | None = None,
        on_loop_closure: LoopClosureHandler | None = None,
    ) -> None:
        loop = asyncio.get_running_loop()
        wiring: list[tuple[str, str, Callable[[bytes], Any], Callable[[Any], None] | None]] = [
            ("odometry", self._keys.odometry, decode_odometry, on_odometry),
            ("scan", self._keys.scan, decode_scan, on_scan),
            ("loop_closure", self._keys.loop_closure, decode_loop_closure, on_loop_closure),
        ]
        for stream, key, decode, handler in wiring:
            if stream not in self._streams or handler is None:
                continue
            self._subscribers.append(
                self._session.declare_subscriber(key, self._callback(stream, decode, handler, loop))
            )
            log.info("zenoh input %s on %s", stream, key)

    def _callback(
        self,
        stream: str,
        decode: Callable[[bytes], Any],
        handler: Callable[[Any], None],
        loop: asyncio.AbstractEventLoop,
    ) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            try:
                message = decode(sample.payload.to_bytes())
            except PayloadError as err:
                self.drops.drop(stream, err)
                return
            with contextlib.suppress(RuntimeError):  # the loop has closed
                loop.call_soon_threadsafe(handler, message)

        return on_sample

    async def close(self) -> None:
        for sub in self._subscribers:
            sub.undeclare()
        self._subscribers.clear()


def _keyframe_body(local_map: LocalMap, keyframe_id: int) -> dict[str, Any]:
    kf = local_map.keyframes[keyframe_id]
    edges = [
        {"to": to, "pose": {"x_m": p.x_m, "y_m": p.y_m, "yaw_rad": p.yaw_rad}}
        for to, p in local_map.graph.neighbours(keyframe_id)
    ]
    o = kf.odom_pose
    return {
        "id": keyframe_id,
        "stamp_s": kf.stamp_s,
        "odom_pose": {"x_m": o.x_m, "y_m": o.y_m, "yaw_rad": o.yaw_rad},
        "vertices_xy": [[round(float(x), 4), round(float(y), 4)] for x, y in kf.polygon.vertices_xy],
        "kinds": [int(k) for k in kf.kinds],
        "edges": edges,
    }


class ZenohOutputs:
    """Publishes what the companion knows; answers map queries; announces itself by liveliness."""

    def __init__(self, session: zenoh.Session, keys: Keys, status_period_s: float = 1.0) -> None:
        self._session = session
        self._keys = keys
        self._period = status_period_s
        self._pub = {
            name: session.declare_publisher(key, encoding=zenoh.Encoding(ENCODING))
            for name, key in (
                ("state", keys.state),
                ("health", keys.health),
                ("setpoint", keys.setpoint),
                ("frontiers", keys.frontiers),
            )
        }
        self._token = session.liveliness().declare_token(keys.alive)
        self._queryable = session.declare_queryable(keys.map, self._answer_map)
        self._snapshot: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._published_keyframes = 0
        self._last_status = -1e9
        self._last_state = ""

    def _put(self, name: str, kind: str, body: dict[str, Any]) -> None:
        self._pub[name].put(dumps(kind, body))

    def update(
        self, state: str, reason: str, health: dict[str, Any], local_map: LocalMap, setpoint: Setpoint | None
    ) -> None:
        """Called by the service after each step and state change; throttles the slow topics."""
        new_ids = sorted(local_map.keyframes)[self._published_keyframes :]
        bodies = [_keyframe_body(local_map, k) for k in new_ids]
        for body in bodies:
            self._session.put(
                self._keys.keyframe(body["id"]), dumps("keyframe", body), encoding=zenoh.Encoding(ENCODING)
            )
        self._published_keyframes += len(new_ids)
        if setpoint is not None:
            self._put("setpoint", "setpoint", {"x_m": setpoint.x_m, "y_m": setpoint.y_m, "yaw_rad": setpoint.yaw_rad})
        now = time.monotonic()
        if state != self._last_state or now - self._last_status >= self._period:
            self._last_state = state
            self._last_status = now
            # The queryable answers from this snapshot, taken between steps (never mid-update).
            snapshot = [_keyframe_body(local_map, k) for k in sorted(local_map.keyframes)]
            with self._lock:
                self._snapshot = snapshot
            self._put("state", "state", {"state": state, "reason": reason, "keyframes": len(local_map)})
            self._put("health", "health", health)
            self._put(
                "frontiers",
                "frontiers",
                {"open": local_map.open_frontier_count(), "keyframes_with_open": _keyframes_with_open(local_map)},
            )

    def _answer_map(self, query: zenoh.Query) -> None:
        with self._lock:
            bodies = self._snapshot
        query.reply(self._keys.map, dumps("map", {"keyframes": bodies}), encoding=zenoh.Encoding(ENCODING))

    async def close(self) -> None:
        self._queryable.undeclare()
        self._token.undeclare()
        for pub in self._pub.values():
            pub.undeclare()


def _keyframes_with_open(local_map: LocalMap) -> list[int]:
    return [k for k, kf in local_map.keyframes.items() if kf.open_frontier_indices().size]
