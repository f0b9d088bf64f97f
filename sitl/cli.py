"""``sitl`` command line: ``sitl run`` puts the simulated vehicle on the wire as a MAVLink
autopilot (PX4 or ArduPilot flavour), the way PX4 SITL and ArduPilot SITL present themselves."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from functools import partial
from pathlib import Path
from types import FrameType

from companion.argtypes import checked, noise_scale, number, seed
from companion.config import check_mavlink_url, check_zenoh_endpoint
from companion.links.zenoh_keys import Keys
from sitl.errors import SitlError
from sitl.map_generator import MapGenParams
from sitl.world import World, load_world

# URLs, endpoints and key chunks as the companion's config checks its own.
_mavlink_url = checked(check_mavlink_url)
_listen_endpoint = checked(partial(check_zenoh_endpoint, listening=True))
_key_prefix = checked(Keys)
_vehicle_name = checked(partial(Keys, "companion"))


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sitl", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run the simulated vehicle as a MAVLink autopilot")
    run.add_argument("--map", required=True, type=Path, help="GeoJSON map (see config/maps/README.md)")
    run.add_argument("--autopilot", choices=("px4", "ardupilot"), default="px4")
    run.add_argument(
        "--mavlink",
        action="append",
        type=_mavlink_url,
        metavar="URL",
        help="pymavlink connection, repeatable (default: px4 udpout:127.0.0.1:14540, "
        "ardupilot tcpin:127.0.0.1:5760, as their SITLs)",
    )
    run.add_argument(
        "--speedup", type=number(float, above_low=True), default=1.0, help="simulation time per wall time (default 1)"
    )
    run.add_argument("--seed", type=seed(), default=1)
    run.add_argument("--noise-scale", type=noise_scale(), default=1.0, help="odometry drift scale (0 = perfect)")
    run.add_argument("--max-time", type=number(float), help="stop after this many simulated seconds")
    run.add_argument(
        "--ekf-delay",
        type=number(float),
        default=2.0,
        help="ArduPilot flavour: seconds after boot before arming is possible (real SITL: about 40)",
    )
    run.add_argument(
        "--zenoh",
        nargs="?",
        const="tcp/127.0.0.1:7447",
        type=_listen_endpoint,
        metavar="ENDPOINT",
        help="also publish scans, odometry and loop closures on Zenoh, listening on ENDPOINT "
        "(default tcp/127.0.0.1:7447; multicast scouting off)",
    )
    run.add_argument("--zenoh-prefix", type=_key_prefix, default="companion", help="key prefix (default companion)")
    run.add_argument(
        "--vehicle-name", type=_vehicle_name, default="sitl", help="vehicle name in the keys (default sitl)"
    )
    run.add_argument("--report", type=Path, help="write the ground-truth report (coverage, collisions) here on exit")
    sensor = sub.add_parser("sensor", help="only the depth sensor and SLAM, following an external autopilot")
    sensor.add_argument("--map", required=True, type=Path, help="GeoJSON map; the autopilot's origin is its start")
    sensor.add_argument(
        "--pose-from", required=True, type=_mavlink_url, metavar="URL", help="pymavlink URL of the autopilot"
    )
    sensor.add_argument(
        "--zenoh", type=_listen_endpoint, default="tcp/127.0.0.1:7447", metavar="ENDPOINT", help="Zenoh listen endpoint"
    )
    sensor.add_argument("--zenoh-prefix", type=_key_prefix, default="companion")
    sensor.add_argument("--vehicle-name", type=_vehicle_name, default="sitl")
    sensor.add_argument("--seed", type=seed(), default=1)
    gen = sub.add_parser("mapgen", help="write a random building map (rooms, doors, furniture) for exploration tests")
    gen.add_argument("--seed", type=seed(), default=1, help="the same seed gives the same map")
    gen.add_argument("--width", type=float, default=24.0, help="building width in metres (default 24)")
    gen.add_argument("--height", type=float, default=16.0, help="building height in metres (default 16)")
    d = MapGenParams()
    gen.add_argument("--min-room", type=float, default=d.min_room_m, help="no room narrower, m (default %(default)g)")
    gen.add_argument("--door-min", type=float, default=d.door_min_m, help="narrowest door, m (default %(default)g)")
    gen.add_argument("--door-max", type=float, default=d.door_max_m, help="widest door, m (default %(default)g)")
    gen.add_argument(
        "--furniture", type=int, default=d.furniture_max_per_room, help="most pieces a room (default %(default)d)"
    )
    gen.add_argument("--out", required=True, type=Path, help="GeoJSON file to write")
    return parser


def _mapgen(args: argparse.Namespace) -> int:
    from sitl.map_generator import write_generated_map

    try:
        params = MapGenParams(
            width_m=args.width,
            height_m=args.height,
            min_room_m=args.min_room,
            door_min_m=args.door_min,
            door_max_m=args.door_max,
            furniture_max_per_room=args.furniture,
        )
        data = write_generated_map(args.out, args.seed, params)
    except (SitlError, OSError) as err:
        print(f"sitl: {err}", file=sys.stderr)
        return 2
    print(f"sitl: wrote {args.out}: {data['description']}")
    return 0


def _sensor(args: argparse.Namespace, world: World) -> int:
    from companion.errors import CompanionError
    from companion.links.zenoh_keys import Keys
    from companion.links.zenoh_link import ZenohSettings, open_session
    from sitl.sensor_node import SensorNode

    try:
        session = open_session(ZenohSettings(listen=(args.zenoh,)))
    except CompanionError as err:
        print(f"sitl: {err}", file=sys.stderr)
        return 2
    try:
        node = SensorNode(world, args.pose_from, session, Keys(args.zenoh_prefix, args.vehicle_name), args.seed)

        def _stop(signum: int, frame: FrameType | None) -> None:
            node.stop()

        signal.signal(signal.SIGTERM, _stop)
        signal.signal(signal.SIGINT, _stop)
        logging.getLogger("sitl").info("sensor following %s, publishing on %s", args.pose_from, args.zenoh)
        try:
            node.run()
        except TimeoutError as err:
            print(f"sitl: {args.pose_from}: {err}", file=sys.stderr)
            return 2
        finally:
            node.close()
    finally:
        session.close()
    logging.getLogger("sitl").info("sensor stopped after %d scans", node.scans)
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stderr)
    if args.command == "mapgen":
        return _mapgen(args)
    try:
        world = load_world(args.map)
    except SitlError as err:
        print(f"sitl: {err}", file=sys.stderr)
        return 2
    if args.command == "sensor":
        return _sensor(args, world)
    from sitl.autopilot import Flavour
    from sitl.mavlink_vehicle import DEFAULT_URL, MavlinkVehicle, VehicleOptions

    flavour = Flavour(args.autopilot)
    urls = tuple(args.mavlink or [DEFAULT_URL[flavour]])
    options = VehicleOptions(
        flavour,
        urls,
        speedup=args.speedup,
        seed=args.seed,
        noise_scale=args.noise_scale,
        max_time_s=args.max_time,
        position_estimate_after_s=args.ekf_delay,
    )
    try:
        vehicle = MavlinkVehicle(world, options)
    except OSError as err:
        print(f"sitl: cannot open {', '.join(urls)}: {err}", file=sys.stderr)
        return 2

    def _stop(signum: int, frame: FrameType | None) -> None:
        vehicle.stop()

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    logging.getLogger("sitl").info(
        "%s vehicle on %s, map %s, speed-up %.1f", flavour.value, ", ".join(urls), args.map, args.speedup
    )
    session = None
    if args.zenoh:
        from companion.errors import CompanionError
        from companion.links.zenoh_keys import Keys
        from companion.links.zenoh_link import ZenohSettings, open_session
        from sitl.zenoh_sensor import ZenohSensorPublisher

        try:
            session = open_session(ZenohSettings(listen=(args.zenoh,)))
        except CompanionError as err:
            print(f"sitl: {err}", file=sys.stderr)
            return 2
        publisher = ZenohSensorPublisher(session, Keys(args.zenoh_prefix, args.vehicle_name))
        vehicle.on_frame = lambda frame: publisher.publish(frame, vehicle.local_estimate)
        logging.getLogger("sitl").info("publishing sensors on Zenoh, listening on %s", args.zenoh)
    try:
        vehicle.run()
    finally:
        if session is not None:
            session.close()
    report = vehicle.report()
    if args.report:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(json.dumps(report, indent=2) + "\n")
    logging.getLogger("sitl").info("stopped: %s", json.dumps(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
