import json
import math
import warnings

import numpy as np
import pytest

from companion.core.geometry import Pose2
from sitl.depth_sensor import DepthSensor, SensorParams, cast_rays
from sitl.errors import MapError
from sitl.world import MAX_SIDE_M, load_world
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


def test_a_map_wider_than_the_simulator_takes_is_refused_before_any_grid_is_built(tmp_path):
    """The coverage grids grow with the area: a 100 km square asked for 1.8 TiB and died with a
    MemoryError traceback. Over ``MAX_SIDE_M`` a side the map is refused, naming its size; at
    the limit it loads (one side at the limit is enough to refuse: a long thin map too)."""
    ok = write_map(tmp_path / "ok.geojson", square(0, 0, MAX_SIDE_M, 10), [], (5.0, 5.0))
    assert load_world(ok).bounds == (0.0, 0.0, MAX_SIDE_M, 10.0)
    wide = write_map(tmp_path / "wide.geojson", square(0, 0, 10, MAX_SIDE_M + 1), [], (5.0, 5.0))
    with pytest.raises(MapError, match=f"10 x {MAX_SIDE_M + 1:g} m") as err:
        load_world(wide)
    assert "wide.geojson" in str(err.value)


def test_a_nan_coordinate_is_a_map_error_without_a_warning(tmp_path):
    """shapely warns on a NaN coordinate before the map's own check names it: the user sees the
    one clear error, not a RuntimeWarning from inside shapely first."""
    p = write_map(tmp_path / "nan.geojson", square(0, 0, 10, 10), [], (5.0, 5.0))
    data = json.loads(p.read_text())
    data["features"][0]["geometry"]["coordinates"][0][2][1] = math.nan  # Python's json writes NaN
    p.write_text(json.dumps(data))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(MapError, match="not a valid polygon"):
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


def test_the_holes_of_an_obstacle_polygon_are_walls_the_sensor_sees(tmp_path):
    """Walls drawn as one polygon round the rooms they enclose (its holes are the rooms): the
    rooms are free space, and their walls are walls. Before, only outer rings were walls, so
    the sensor saw through every such wall and the vehicle flew on through them."""
    rings = [square(0, 0, 20, 10), square(1, 1, 9, 9), square(11, 1, 19, 9)]
    geometry = {"type": "Polygon", "coordinates": rings}
    walls = {"type": "Feature", "properties": {"kind": "obstacle"}, "geometry": geometry}
    path = write_map(tmp_path / "m.geojson", square(0, 0, 20, 10), [], (5.0, 5.0))
    data = json.loads(path.read_text())
    data["features"].insert(1, walls)
    path.write_text(json.dumps(data))
    w = load_world(path)
    assert w.free.area == pytest.approx(2 * 64.0)
    sensor = DepthSensor(w.walls, SensorParams(range_noise_m=0.0), np.random.default_rng(0))
    east = sensor.scan(Pose2(5.0, 5.0, 0.0), 0.0)  # the room's east wall is 4 m ahead
    assert np.allclose(east.ranges_m[len(east.ranges_m) // 2], 4.0, atol=0.02)


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
