"""``companion monitor``: a live table of the Zenoh keys seen (rate, age, size, a short summary),
or ``--echo KEY`` to print samples as they arrive. Works with any publisher on the bus."""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from rich.console import Console
from rich.live import Live
from rich.table import Table

from companion.links.zenoh_link import ZenohSettings, check_key_expr, open_session


@dataclass
class KeyStats:
    """What the monitor knows about one key."""

    count: int = 0
    last_wall_s: float = 0.0
    last_size: int = 0
    summary: str = ""
    stamps: deque[float] = field(default_factory=lambda: deque(maxlen=50))

    def rate_hz(self, now: float) -> float:
        recent = [t for t in self.stamps if now - t <= 5.0]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / max(recent[-1] - recent[0], 1e-6)


def summarize(payload: bytes, limit: int = 60) -> str:
    """A one-line summary of a payload: JSON type and a few scalar fields, else its size."""
    try:
        data = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return f"<{len(payload)} bytes, not JSON>"
    if not isinstance(data, dict):
        return str(data)[:limit]
    parts = [str(data.get("type", ""))]
    for k, v in data.items():
        if k in ("type", "schema"):
            continue
        if isinstance(v, (int, float, str, bool)) or v is None:
            parts.append(f"{k}={round(v, 3) if isinstance(v, float) else v}")
        elif isinstance(v, list):
            parts.append(f"{k}[{len(v)}]")
    return " ".join(p for p in parts if p)[:limit]


class Monitor:
    """Collects samples from a Zenoh subscription (on Zenoh's thread) for display."""

    def __init__(self) -> None:
        self.stats: dict[str, KeyStats] = {}
        self._lock = threading.Lock()

    def on_sample(self, key: str, payload: bytes) -> None:
        now = time.monotonic()
        with self._lock:
            s = self.stats.setdefault(key, KeyStats())
            s.count += 1
            s.last_wall_s = now
            s.last_size = len(payload)
            s.summary = summarize(payload)
            s.stamps.append(now)

    def table(self) -> Table:
        now = time.monotonic()
        t = Table(title="companion monitor", expand=False)
        for col in ("key", "rate Hz", "age s", "bytes", "count", "last value"):
            t.add_column(col, no_wrap=col != "last value")
        with self._lock:
            items = sorted(self.stats.items())
            rows = [
                (k, f"{s.rate_hz(now):6.1f}", f"{now - s.last_wall_s:5.1f}", str(s.last_size), str(s.count), s.summary)
                for k, s in items
            ]
        for row in rows:
            t.add_row(*row)
        return t


def run_monitor(
    keyexpr: str,
    connect: list[str],
    duration_s: float | None,
    once: bool,
    echo: str | None,
    console: Console,
) -> int:
    """Watch the bus; 0 when something was seen, 1 when nothing was reachable or published."""
    check_key_expr(echo or keyexpr)
    settings = ZenohSettings(mode="peer", connect=tuple(connect))
    monitor = Monitor()
    session = open_session(settings)
    try:

        def on_sample(sample: Any) -> None:
            key = str(sample.key_expr)
            payload = sample.payload.to_bytes()
            monitor.on_sample(key, payload)
            if echo is not None:
                console.print(f"[bold]{key}[/] {payload.decode(errors='replace')}", soft_wrap=True)

        sub = session.declare_subscriber(echo or keyexpr, on_sample)
        limit = duration_s if duration_s is not None else (3.0 if once else None)
        start = time.monotonic()
        try:
            if echo is not None or once:
                while limit is None or time.monotonic() - start < limit:
                    time.sleep(0.1)
                    if once and monitor.stats and time.monotonic() - start >= min(limit or 3.0, 2.0):
                        break
                if once and monitor.stats:
                    console.print(monitor.table())
            else:
                with Live(monitor.table(), console=console, refresh_per_second=2) as live:
                    while limit is None or time.monotonic() - start < limit:
                        time.sleep(0.5)
                        live.update(monitor.table())
        except KeyboardInterrupt:
            pass
        finally:
            sub.undeclare()
        if not monitor.stats:
            peers = list(session.info.peers_zid()) + list(session.info.routers_zid())
            where = ", ".join(connect) or "the local network (no --connect given)"
            if not peers:
                console.print(f"[red]nothing reachable[/] at {where}: is the companion or sitl running?")
            else:
                console.print(f"connected to {len(peers)} node(s) at {where}, but nothing published on {keyexpr}")
            return 1
        return 0
    finally:
        session.close()
