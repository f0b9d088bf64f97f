"""Random building maps (sitl/map_generator.py): valid, reachable, deterministic, and explored."""

import json

import pytest
import shapely

from sitl.cli import main as sitl_main
from sitl.errors import MapError
from sitl.map_generator import MapGenParams, generate_map, write_generated_map
from sitl.runner import run_exploration
from sitl.world import MAX_SIDE_M, load_world

BERTH_M = MapGenParams().berth_m


def _write(tmp_path, seed, params=None):
    path = tmp_path / f"gen{seed}.geojson"
    write_generated_map(path, seed, params)
    return path


def test_the_same_seed_gives_the_same_map_and_another_seed_another():
    assert generate_map(7) == generate_map(7)
    assert generate_map(7) != generate_map(8)


@pytest.mark.parametrize("seed", range(1, 16))
def test_every_generated_map_loads_and_every_room_is_reachable_with_the_vehicles_berth(tmp_path, seed):
    world = load_world(_write(tmp_path, seed))
    minx, miny, maxx, maxy = world.bounds
    assert (maxx - minx, maxy - miny) == (24.0, 16.0)
    # Where the vehicle's centre may go: one piece, holding the start. A door narrower than
    # the berth, or furniture closing a passage, would split it.
    core = world.free.buffer(-BERTH_M)
    assert core.geom_type == "Polygon"
    assert core.contains(shapely.Point(world.start.x_m, world.start.y_m))
    # And it reaches nearly all the free space: no room is left out of reach.
    assert core.buffer(BERTH_M).area >= 0.9 * world.free.area


def test_maps_have_rooms_doors_and_furniture_across_seeds():
    rooms = [int(generate_map(s)["description"].split(", ")[1].split()[0]) for s in range(1, 21)]
    obstacles = [len(generate_map(s)["features"]) - 2 for s in range(1, 21)]
    assert min(rooms) >= 2  # the building is always divided
    assert max(rooms) >= 10
    assert all(n > 0 for n in obstacles)


def test_a_building_too_small_for_a_room_is_a_clear_error():
    with pytest.raises(MapError, match="at least"):
        generate_map(1, MapGenParams(width_m=2.0))


def test_a_building_wider_than_the_simulator_takes_is_a_clear_error(tmp_path, capsys):
    """``sitl mapgen`` must not write a map ``load_world`` then refuses (over ``MAX_SIDE_M``)."""
    with pytest.raises(MapError, match="at most"):
        generate_map(1, MapGenParams(height_m=MAX_SIDE_M + 1.0))
    out = tmp_path / "wide.geojson"
    assert sitl_main(["mapgen", "--width", str(MAX_SIDE_M + 1.0), "--out", str(out)]) == 2
    assert not out.exists() and "at most" in capsys.readouterr().err


def test_sitl_mapgen_writes_a_map_the_simulator_loads(tmp_path, capsys):
    out = tmp_path / "maps" / "g.geojson"
    assert sitl_main(["mapgen", "--seed", "4", "--width", "14", "--height", "10", "--out", str(out)]) == 0
    world = load_world(out)
    assert world.bounds == (0.0, 0.0, 14.0, 10.0)
    assert "wrote" in capsys.readouterr().out
    assert sitl_main(["mapgen", "--seed", "4", "--width", "1", "--out", str(out)]) == 2
    assert "at least" in capsys.readouterr().err


def test_sitl_mapgen_takes_the_rooms_doors_and_furniture_from_its_flags(tmp_path, capsys):
    """The CLI builds the map the parameters give (the new-shape sets in docs/benchmarks.md are
    written this way), and refuses doors that cannot be."""
    out = tmp_path / "narrow.geojson"
    flags = ["--seed", "410", "--width", "14", "--height", "12", "--min-room", "3", "--door-min", "0.9"]
    assert sitl_main(["mapgen", *flags, "--door-max", "1.2", "--furniture", "3", "--out", str(out)]) == 0
    params = MapGenParams(
        width_m=14.0, height_m=12.0, min_room_m=3.0, door_min_m=0.9, door_max_m=1.2, furniture_max_per_room=3
    )
    assert json.loads(out.read_text()) == json.loads(json.dumps(generate_map(410, params)))
    assert "doors 0.9-1.2 m" in capsys.readouterr().out
    assert generate_map(410, params) != generate_map(410, MapGenParams(width_m=14.0, height_m=12.0, min_room_m=3.0))
    assert sitl_main(["mapgen", "--door-min", "1.3", "--door-max", "1.2", "--out", str(out)]) == 2
    assert "doors must be" in capsys.readouterr().err
    assert sitl_main(["mapgen", "--furniture", "-1", "--out", str(out)]) == 2
    assert "furniture" in capsys.readouterr().err


def test_the_polygon_explorer_covers_a_generated_building_it_was_never_tuned_for(tmp_path):
    """A map no one drew: rooms, doors and furniture from a seed, explored with drift."""
    world = load_world(_write(tmp_path, 3, MapGenParams(width_m=14.0, height_m=10.0)))
    r = run_exploration(world, "polygon", seed=1, noise_scale=1.0, max_time_s=900).report
    assert r["collisions"] == 0
    assert r["termination"] == "complete"
    assert r["coverage"] >= 0.99
