"""Start ``sitl run`` (and other commands) as subprocesses for tests: free loopback ports, logs
piped into the test log, always stopped."""

from __future__ import annotations

import logging
import random
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
log = logging.getLogger("tests.subprocess")


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A free loopback port below the kernel's ephemeral range: a port the kernel handed out and
    took back is its to give again, and a `udpout:` socket opened meanwhile (the simulated
    vehicle's, say) could be bound to it before the companion binds it."""
    high = _ephemeral_low()
    low = 20000 if high > 21000 else 1024
    for _ in range(200):
        port = random.randrange(low, high)
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError("no free loopback port below the ephemeral range")


def _ephemeral_low() -> int:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def _pipe(stream: object, name: str) -> None:
    for line in iter(stream.readline, ""):  # type: ignore[attr-defined]
        log.info("[%s] %s", name, line.rstrip())


@contextmanager
def running(args: list[str], name: str) -> Iterator[subprocess.Popen[str]]:
    """Run ``python -m <args>`` from the repository; terminate (then kill) it on exit."""
    proc = subprocess.Popen(
        [sys.executable, "-m", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    reader = threading.Thread(target=_pipe, args=(proc.stdout, name), daemon=True)
    reader.start()
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        reader.join(2)


def run_companion(config: Path, report: Path, timeout_s: float) -> subprocess.CompletedProcess[str]:
    """``companion run`` to the end, its output captured for assertion messages."""
    return subprocess.run(
        [sys.executable, "-m", "companion.cli", "run", "--config", str(config), "--report", str(report)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


@contextmanager
def sitl_vehicle(
    autopilot: str,
    report: Path,
    speedup: float = 10.0,
    map_path: Path = ROOT / "config/maps/room.geojson",
    extra: tuple[str, ...] = (),
) -> Iterator[str]:
    """A ``sitl run`` vehicle on a free loopback port; yields the companion's connection URL."""
    if autopilot == "px4":
        port = free_port()
        vehicle_url, companion_url = f"udpout:127.0.0.1:{port}", f"udpin:127.0.0.1:{port}"
    else:
        port = free_port(socket.SOCK_STREAM)
        vehicle_url, companion_url = f"tcpin:127.0.0.1:{port}", f"tcp:127.0.0.1:{port}"
    args = ["sitl.cli", "run", "--map", str(map_path), "--autopilot", autopilot, "--mavlink", vehicle_url]
    args += ["--speedup", str(speedup), "--seed", "1", "--report", str(report), *extra]
    with running(args, f"sitl-{autopilot}"):
        yield companion_url
