"""Every Zenoh key expression the product uses, built from one prefix and a vehicle name.

Inputs (published by sensors / SLAM, or by ``sitl run --zenoh``):
``<prefix>/<vehicle>/sensors/scan``, ``.../sensors/odometry``, ``.../slam/loop_closure``.
Outputs (published by the companion): ``.../companion/state``, ``.../companion/health``,
``.../companion/setpoint``, ``.../companion/map/keyframes/<id>``, ``.../companion/frontiers``;
the liveliness token ``.../companion/alive`` and the queryable ``.../companion/map``.
See docs/interfaces.md for payloads, units, frames and rates.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

_CHUNK = re.compile(r"^[A-Za-z0-9_\-.]+$")


@dataclass(frozen=True, slots=True)
class Keys:
    prefix: str = "companion"
    vehicle: str = "sitl"

    def __post_init__(self) -> None:
        for part in (*self.prefix.split("/"), self.vehicle):
            if not _CHUNK.match(part):
                raise ValueError(f"key chunk {part!r} must be letters, digits, '_', '-' or '.'")

    @property
    def root(self) -> str:
        return f"{self.prefix}/{self.vehicle}"

    @property
    def scan(self) -> str:
        return f"{self.root}/sensors/scan"

    @property
    def odometry(self) -> str:
        return f"{self.root}/sensors/odometry"

    @property
    def loop_closure(self) -> str:
        return f"{self.root}/slam/loop_closure"

    @property
    def state(self) -> str:
        return f"{self.root}/companion/state"

    @property
    def health(self) -> str:
        return f"{self.root}/companion/health"

    @property
    def setpoint(self) -> str:
        return f"{self.root}/companion/setpoint"

    @property
    def frontiers(self) -> str:
        return f"{self.root}/companion/frontiers"

    def keyframe(self, keyframe_id: int) -> str:
        return f"{self.root}/companion/map/keyframes/{keyframe_id}"

    @property
    def map(self) -> str:
        return f"{self.root}/companion/map"

    @property
    def alive(self) -> str:
        return f"{self.root}/companion/alive"

    @property
    def everything(self) -> str:
        return f"{self.root}/**"
