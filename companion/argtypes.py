"""Argument types for the command lines (``companion`` and ``sitl``): a number, URL or name is
checked where it is typed, so a bad one is a usage error naming the option, never a traceback
deep in a run (or a flight with it)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

MAX_NOISE_SCALE = 10.0  # ten times the thesis's drift: far past any odometry worth exploring with


def number(
    kind: type[float] | type[int], low: float = 0.0, high: float = math.inf, above_low: bool = False
) -> Callable[[str], float]:
    """A finite ``kind`` in [``low``, ``high``] (or (``low``, ``high``] with ``above_low``)."""

    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected {'an integer' if kind is int else 'a number'}, got {text!r}"
            ) from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if value < low or (above_low and value == low):
            raise argparse.ArgumentTypeError(f"must be {'above' if above_low else 'at least'} {low:g}, got {text}")
        if value > high:
            raise argparse.ArgumentTypeError(f"must be at most {high:g}, got {text}")
        return value

    return parse


def checked(check: Callable[[str], object]) -> Callable[[str], str]:
    """The text, if ``check`` (a config-side validator) takes it; its ValueError as a usage error."""

    def parse(text: str) -> str:
        try:
            check(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None
        return text

    return parse


def seed() -> Callable[[str], float]:
    """A random seed: numpy takes any non-negative integer."""
    return number(int)


def noise_scale() -> Callable[[str], float]:
    """The odometry drift's scale: 0 (perfect) to :data:`MAX_NOISE_SCALE`."""
    return number(float, 0.0, MAX_NOISE_SCALE)
