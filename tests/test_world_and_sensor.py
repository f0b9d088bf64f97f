import json
import math

import numpy as np
import pytest

from companion.core.geometry import Pose2
from sitl.depth_sensor import DepthSensor, SensorParams, cast_rays
from sitl.errors import MapError
from sitl.world import load_world
from tests.conftest import square, write_map


def test_shipped_maps_load(shipped_maps):
    paths = sorted(shipped_maps.glob("*.geojson"))
    assert {p.stem for p in paths} >= {
        "room",
        "office",
        "loop",
        "warehouse",
        "lshape",
        "maze",
        "clutter",
        "hotel",
        "hall",
        "rotunda",
        "longhall",
        "apartment",
        "gallery",
        "cave",
        "offices2",
        "nook",
        "strip",
        "corridor",
    }
    for path in paths:
        w = load_world(path)
        assert w.name == path.stem and w.free.area > 30.0
        assert w.free.contains(__import__("shapely").Point(w.start.x_m, w.start.y_m))
        assert w.walls.shape[1:] == (2, 2)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("not json", "not valid JSON"),
        (json.dumps({"type": "Feature"}), "FeatureCollection"),
        (json.dumps({"type": "FeatureCollection", "features": []}), "exactly one boundary"),
    ],
)
def test_malformed_maps_get_clear_errors_naming_the_file(tmp_path, text, needle):
    p = tmp_path / "bad.geojson"
    p.write_text(text)
    with pytest.raises(MapError, match=needle) as err:
        load_world(p)
    assert "bad.geojson" in str(err.value)


def test_start_inside_an_obstacle_is_refused(tmp_path):
    p = write_map(tmp_path / "m.geojson", square(0, 0, 10, 10), [square(4, 4, 6, 6)], (5.0, 5.0))
    with pytest.raises(MapError, match="not in free space"):
        load_world(p)


def test_boundary_that_is_not_a_polygon_is_refused(tmp_path):
    p = tmp_path / "line.geojson"
    p.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {"kind": "boundary"},
                        "geometry": {"type": "LineString", "coordinates": [[0, 0], [1, 1]]},
                    },
                    {
                        "type": "Feature",
                        "properties": {"kind": "start"},
                        "geometry": {"type": "Point", "coordinates": [0.5, 0.5]},
                    },
                ],
            }
        )
    )
    with pytest.raises(MapError, match="must be a Polygon"):
        load_world(p)


def test_rays_hit_a_wall_at_the_analytic_distance():
    wall = np.array([[[3.0, -5.0], [3.0, 5.0]]])
    angles = np.array([0.0, math.radians(45), math.radians(80), math.pi])
    d = cast_rays(np.array([1.0, 0.0]), angles, wall, 5.0)
    assert math.isclose(d[0], 2.0)
    assert math.isclose(d[1], 2.0 * math.sqrt(2.0))
    assert math.isinf(d[2])  # 2 / cos(80 deg) = 11.5 m, beyond range
    assert math.isinf(d[3])  # pointing away


def test_sensor_reports_max_range_for_no_return(tmp_path):
    w = load_world(write_map(tmp_path / "m.geojson", square(0, 0, 30, 30), [], (1.0, 15.0)))
    sensor = DepthSensor(w.walls, SensorParams(range_noise_m=0.0), np.random.default_rng(0))
    s = sensor.scan(Pose2(1.0, 15.0, math.pi), 0.0)  # facing the wall 1 m behind
    assert np.allclose(s.ranges_m[len(s.ranges_m) // 2], 1.0, atol=0.02)
    s2 = sensor.scan(Pose2(1.0, 15.0, 0.0), 0.0)  # facing 29 m of open room
    assert np.all(s2.ranges_m == 5.0)
