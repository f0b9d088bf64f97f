"""``companion`` command line: ``companion sim`` explores in the in-process simulator; ``companion run``
runs the service against a vehicle (real or ``sitl run``) as its config says."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

from pydantic import ValidationError
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn

from companion.app import LoopClosureSource, tuning_for
from companion.argtypes import checked, noise_scale, number, seed
from companion.config import ExplorationConfig, check_zenoh_endpoint
from companion.errors import CompanionError
from sitl.errors import SitlError
from sitl.runner import PLANNERS, RunTrace, run_exploration
from sitl.simulation import SimParams
from sitl.slam import SlamParams
from sitl.world import World, load_world


def _exploration_value(field: str):  # type: ignore[no-untyped-def]
    """A number the config's ``exploration.<field>`` would take (its bounds, one place for both)."""

    def parse(text: str) -> float:
        value = float(number(float)(text))
        try:
            ExplorationConfig.model_validate({field: value})
        except ValidationError as exc:
            raise argparse.ArgumentTypeError(f"{exc.errors()[0]['msg'].lower()}, got {text}") from None
        return value

    return parse


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sim = sub.add_parser("sim", help="explore a map with the in-process simulated vehicle")
    sim.add_argument("--map", required=True, type=Path, help="GeoJSON map (see config/maps/README.md)")
    sim.add_argument("--planner", choices=PLANNERS, default="polygon")
    sim.add_argument("--seed", type=seed(), default=1)
    sim.add_argument(
        "--noise-scale",
        type=noise_scale(),
        default=1.0,
        help="odometry drift scale (0 = perfect)",
    )
    sim.add_argument(
        "--max-time",
        type=number(float),
        default=1800.0,
        help="simulated seconds before timing out",
    )
    sim.add_argument(
        "--input-latency",
        type=number(float),
        default=0.0,
        metavar="S",
        help="hand the planner each scan and odometry sample S seconds late, as a link does (default 0)",
    )
    sim.add_argument(
        "--loop-closures",
        choices=("simulated", "scan-matching", "none"),
        default="simulated",
        help="where loop closures come from: the simulated SLAM back end (default; as the service "
        "with inputs.loop_closure: zenoh), the companion's own matching of its views "
        "(scan_matching), or nowhere (none: the map closes new views along the pose graph)",
    )
    sim.add_argument(
        "--no-loop-closures",
        dest="loop_closures",
        action="store_const",
        const="none",
        help="the same as --loop-closures none",
    )
    sim.add_argument(
        "--odometry-drift-per-keyframe",
        type=_exploration_value("odometry_drift_m_per_keyframe"),
        default=0.05,
        metavar="M",
        help="the map's drift margin per keyframe along the pose graph, as "
        "exploration.odometry_drift_m_per_keyframe in a config (default 0.05)",
    )
    sim.add_argument(
        "--odometry-drift-sigma",
        type=_exploration_value("odometry_drift_sigma_m_per_sqrt_m"),
        default=0.1,
        metavar="M",
        help="how far the companion takes the odometry to drift, one sigma per axis after a metre, as "
        "exploration.odometry_drift_sigma_m_per_sqrt_m in a config (default 0.1, the thesis's; "
        "--noise-scale 1): the berth kept from remembered returns grows with it",
    )
    sim.add_argument(
        "--odometry-matching",
        choices=("on", "off"),
        help="correct each keyframe's odometry edge by matching its view to the previous one's, as "
        "exploration.match_odometry_edges in a config (default: on, but off with --loop-closures none)",
    )
    sim.add_argument("--report", type=Path, help="write the JSON report here")
    sim.add_argument("--plots", type=Path, help="write PNG figures into this folder")
    sim.add_argument("--no-baseline", action="store_true", help="with --plots: skip the grid baseline run")
    sim.add_argument("--quiet", action="store_true", help="no progress display")
    run = sub.add_parser("run", help="run the service against a vehicle, as the config says")
    run.add_argument("--config", required=True, type=Path, help="YAML config (see config/*.yaml)")
    run.add_argument("--report", type=Path, help="write the JSON report here at the end")
    run.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    mon = sub.add_parser("monitor", help="watch the companion's (and sensors') Zenoh keys")
    mon.add_argument("keyexpr", nargs="?", default="companion/**", help="key expression (default companion/**)")
    mon.add_argument(
        "--connect",
        action="append",
        type=checked(partial(check_zenoh_endpoint, listening=False)),
        metavar="ENDPOINT",
        help="Zenoh endpoint, repeatable (default tcp/127.0.0.1:7447 and tcp/127.0.0.1:7448: "
        "sitl run --zenoh and the companion in config/sitl-zenoh.yaml)",
    )
    mon.add_argument("--echo", metavar="KEY", help="print the samples of KEY as they arrive")
    mon.add_argument("--duration", type=number(float), help="stop after this many seconds")
    mon.add_argument("--once", action="store_true", help="print the table once (after up to 3 s) and exit")
    return parser


def _explore(
    world: World, args: argparse.Namespace, planner: str, console: Console, latency_s: float = 0.0
) -> RunTrace:
    sources: dict[str, LoopClosureSource] = {"simulated": "back_end", "scan-matching": "scan_matching", "none": "none"}
    source = sources[args.loop_closures]
    explorer_params = tuning_for(source, args.odometry_drift_per_keyframe, args.odometry_drift_sigma)
    if args.odometry_matching is not None:
        matching = replace(explorer_params.odometry_matching, enabled=args.odometry_matching == "on")
        explorer_params = replace(explorer_params, odometry_matching=matching)
    sim_params = None if source == "back_end" else SimParams(slam=SlamParams(enabled=False))

    def explore(progress: Callable[[float, float], None] | None = None) -> RunTrace:
        return run_exploration(
            world,
            planner,
            args.seed,
            args.noise_scale,
            args.max_time,
            sim_params=sim_params,
            explorer_params=explorer_params,
            progress=progress,
            map_label=str(args.map),
            input_latency_s=latency_s,
        )

    if args.quiet:
        return explore()
    with Progress(
        TextColumn(f"[bold]{planner}[/] {world.name}"),
        BarColumn(),
        TextColumn("coverage {task.fields[coverage]:5.1%}  sim {task.fields[sim_s]:6.0f} s"),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("explore", total=1.0, coverage=0.0, sim_s=0.0)

        def progress(sim_s: float, coverage: float) -> None:
            bar.update(task, completed=coverage, coverage=coverage, sim_s=sim_s)

        return explore(progress)


def _outputs_writable(args: argparse.Namespace) -> None:
    """Make the report's folder (and the plots folder, for ``sim``) before the flight, so a path
    that cannot be written fails at once, not after minutes of flying."""
    plots = getattr(args, "plots", None)
    for folder in [*([args.report.parent] if args.report else []), *([plots] if plots else [])]:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CompanionError(f"cannot create {folder}: {exc.strerror or exc}") from None
        if not os.access(folder, os.W_OK):
            raise CompanionError(f"cannot write into {folder}")
    if args.report and args.report.is_dir():
        raise CompanionError(f"--report {args.report} is a folder; give a file name")


def _sim(args: argparse.Namespace, console: Console) -> int:
    world = load_world(args.map)
    _outputs_writable(args)
    trace = _explore(world, args, args.planner, console, args.input_latency)  # the baseline: no latency
    r = trace.report
    console.print(
        f"{r['planner']} on {world.name}: termination [bold]{r['termination']}[/], coverage {r['coverage']:.3f}, "
        f"time {r['exploration_time_s']:.1f} s (99% at {r['time_to_99_s']} s), path {r['path_length_m']:.1f} m, "
        f"collisions {r['collisions']}, keyframes {r['keyframes']}, loop closures {r['loop_closures']}, "
        f"step p50/p99 {r['step_ms']['p50']:.2f}/{r['step_ms']['p99']:.2f} ms"
    )
    if args.report:
        try:
            args.report.write_text(json.dumps(r, indent=2) + "\n")
        except OSError as exc:
            raise CompanionError(f"cannot write {args.report}: {exc.strerror or exc}") from None
        console.print(f"report: {args.report}")
    if args.plots:
        from sitl.plots import write_plots  # matplotlib only when asked for

        baseline = None
        if args.planner == "polygon" and not args.no_baseline:
            baseline = _explore(world, args, "grid", console)
            b = baseline.report
            console.print(
                f"grid baseline: {b['termination']}, coverage {b['coverage']:.3f}, "
                f"time {b['exploration_time_s']:.1f} s "
                f"-> time ratio polygon/grid {r['exploration_time_s'] / max(b['exploration_time_s'], 1e-9):.2f}"
            )
        try:
            for path in write_plots(world, trace, args.plots, baseline):
                console.print(f"plot: {path}")
        except OSError as exc:
            raise CompanionError(f"cannot write the plots into {args.plots}: {exc.strerror or exc}") from None
    return 0 if r["termination"] in ("complete", "unreachable_frontiers_left") and r["collisions"] == 0 else 1


def _run(args: argparse.Namespace) -> int:
    import asyncio
    import logging

    from rich.logging import RichHandler

    from companion.app import run_service
    from companion.config import load_config

    config = load_config(args.config)
    _outputs_writable(args)
    logging.basicConfig(
        level=args.log_level,
        format="%(name)s: %(message)s",
        handlers=[RichHandler(console=Console(stderr=True), show_path=False)],
    )
    return asyncio.run(run_service(config, args.report))


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    console = Console(stderr=False)
    err = Console(stderr=True)
    try:
        if args.command == "sim":
            return _sim(args, console)
        if args.command == "run":
            return _run(args)
        if args.command == "monitor":
            from companion.monitor import run_monitor

            connect = args.connect or ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]
            return run_monitor(args.keyexpr, connect, args.duration, args.once, args.echo, console)
    except (SitlError, CompanionError) as exc:
        err.print(f"[red]error:[/] {exc}")
        return 2
    except KeyboardInterrupt:
        err.print("interrupted")
        return 130
    return 2


if __name__ == "__main__":
    sys.exit(main())
