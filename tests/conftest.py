"""Shared fixtures: small maps written to a temporary folder."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest


def write_map(
    path: Path,
    boundary: list[list[float]],
    obstacles: list[list[list[float]]],
    start: tuple[float, float],
    yaw_deg: float = 0.0,
) -> Path:
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"kind": "boundary"},
            "geometry": {"type": "Polygon", "coordinates": [boundary]},
        }
    ]
    for ob in obstacles:
        features.append(
            {
                "type": "Feature",
                "properties": {"kind": "obstacle"},
                "geometry": {"type": "Polygon", "coordinates": [ob]},
            }
        )
    features.append(
        {
            "type": "Feature",
            "properties": {"kind": "start", "yaw_deg": yaw_deg},
            "geometry": {"type": "Point", "coordinates": list(start)},
        }
    )
    path.write_text(json.dumps({"type": "FeatureCollection", "name": path.stem, "features": features}))
    return path


def square(x0: float, y0: float, x1: float, y1: float) -> list[list[float]]:
    return [[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]


@pytest.fixture
def small_room(tmp_path: Path) -> Path:
    """An 8 x 6 m room with one pillar: explored in well under a minute of sim time."""
    return write_map(
        tmp_path / "small_room.geojson",
        square(0, 0, 8, 6),
        [square(3.5, 2.5, 4.5, 3.5)],
        (1.0, 1.0),
        30.0,
    )


@pytest.fixture
def two_rooms(tmp_path: Path) -> Path:
    """Two rooms joined by a 1.2 m door: the far room needs the planner to go through."""
    wall_a = square(5.0, 0.0, 5.2, 2.4)
    wall_b = square(5.0, 3.6, 5.2, 6.0)
    return write_map(tmp_path / "two_rooms.geojson", square(0, 0, 10, 6), [wall_a, wall_b], (1.0, 3.0), 0.0)


@pytest.fixture
def shipped_maps() -> Path:
    """The maps shipped in config/maps."""
    return Path(__file__).resolve().parents[1] / "config" / "maps"
