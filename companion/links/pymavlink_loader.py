"""Import pymavlink speaking MAVLink 2 (it reads ``MAVLINK20`` at import time), without setting
the variable for the whole process at import of this package."""

from __future__ import annotations

import importlib
import os
from types import ModuleType


def load_mavutil() -> ModuleType:
    """``pymavlink.mavutil`` with the MAVLink 2 ``common``/``ardupilotmega`` dialect."""
    os.environ.setdefault("MAVLINK20", "1")
    os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")
    return importlib.import_module("pymavlink.mavutil")
