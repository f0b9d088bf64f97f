"""Exploration benchmark: every shipped map, seeds 1..N, polygon planner (with drift) against the
grid baseline (perfect poses). Writes JSON results and prints a summary table.

    .venv/bin/python benchmarks/run.py --out out/bench/results.json [--seeds 5] [--maps room office]
        [--generated 10]

``--generated N`` adds N random buildings (sitl/map_generator.py, map seeds 1..N, written next to
the results as ``maps/genK.geojson``): maps nobody tuned the planner for.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.argtypes import number
from sitl.map_generator import write_generated_map
from sitl.runner import FINAL_COVERAGE_TOLERANCE, run_exploration
from sitl.world import load_world


def _write(out: Path, runs: list[dict[str, Any]]) -> None:
    """The results so far, replacing the file whole (never a half-written JSON)."""
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(runs, indent=2) + "\n")
    tmp.replace(out)


def _searching_pct(runs: list[dict[str, Any]], planner: str) -> float:
    """Of a planner's flight time in these runs, the share flown after coverage reached (within
    :data:`~sitl.runner.FINAL_COVERAGE_TOLERANCE`) the value it ended at: search that found nothing."""
    total = sum(r[planner]["exploration_time_s"] for r in runs)
    after = sum(r[planner]["exploration_time_s"] - r[planner]["time_to_final_coverage_s"] for r in runs)
    return 100.0 * after / total if total > 0.0 else 0.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/bench/results.json"))
    parser.add_argument("--seeds", type=number(int, 1), default=5)
    parser.add_argument("--maps", nargs="*", default=None, help="map names in config/maps (default: all)")
    parser.add_argument("--max-time", type=number(float, above_low=True), default=3600.0)
    parser.add_argument(
        "--generated", type=number(int), default=0, help="also this many generated maps (map seeds 1..N)"
    )
    args = parser.parse_args()
    console = Console()
    paths = sorted(Path("config/maps").glob("*.geojson"))
    if args.maps:
        unknown = sorted(set(args.maps) - {p.stem for p in paths})
        if unknown:
            parser.error(f"no such map in config/maps: {', '.join(unknown)}")
        paths = [p for p in paths if p.stem in args.maps]
    try:  # before hours of flights, not after them
        args.out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parser.error(f"cannot create {args.out.parent}: {err.strerror or err}")
    if args.generated > 0:
        for k in range(1, args.generated + 1):
            path = args.out.parent / "maps" / f"gen{k}.geojson"
            write_generated_map(path, k)
            paths.append(path)
    runs = []
    for path in paths:
        world = load_world(path)
        for seed in range(1, args.seeds + 1):
            row = {}
            for planner in ("polygon", "grid"):
                t0 = time.perf_counter()
                report = run_exploration(
                    world, planner, seed=seed, max_time_s=args.max_time, map_label=path.stem
                ).report
                report["wall_s"] = round(time.perf_counter() - t0, 2)
                row[planner] = report
                console.print(
                    f"{path.stem} seed {seed} {planner}: {report['termination']} cov {report['coverage']:.3f} "
                    f"t {report['exploration_time_s']:.0f} s, step p99 {report['step_ms']['p99']:.1f} ms"
                )
            # A ratio only against a baseline that explored the map: the grid can crash (gallery
            # seed 2) or be shut in behind a door too narrow even for its tight clearance.
            grid = row["grid"]
            comparable = grid["termination"] == "complete" and grid["coverage"] >= 0.99 and not grid["collisions"]
            row["time_ratio"] = (
                round(row["polygon"]["exploration_time_s"] / grid["exploration_time_s"], 3) if comparable else None
            )
            t99p, t99g = row["polygon"]["time_to_99_s"], grid["time_to_99_s"]
            row["time_to_99_ratio"] = None if not (comparable and t99p and t99g) else round(t99p / t99g, 3)
            runs.append({"map": path.stem, "seed": seed, **row})
            _write(args.out, runs)  # after every pair of runs: an interrupted bench keeps what it flew
    table = Table(title="polygon (drift) vs grid (perfect poses)")
    for col in (
        "map",
        "runs",
        "coverage min",
        "grid coverage min",
        "collisions",
        "complete",
        "time ratio median",
        "t99 ratio median",
        "search after coverage [%] (grid)",
        "step p99 max [ms]",
    ):
        table.add_column(col)
    for name in sorted({r["map"] for r in runs}):
        rs = [r for r in runs if r["map"] == name]
        t99 = [r["time_to_99_ratio"] for r in rs if r["time_to_99_ratio"]]
        ratios = [r["time_ratio"] for r in rs if r["time_ratio"] is not None]
        table.add_row(
            name,
            str(len(rs)),
            f"{min(r['polygon']['coverage'] for r in rs):.3f}",
            f"{min(r['grid']['coverage'] for r in rs):.3f}",
            str(sum(r["polygon"]["collisions"] for r in rs)),
            f"{sum(r['polygon']['termination'] == 'complete' for r in rs)}/{len(rs)}",
            f"{statistics.median(ratios):.2f} ({len(ratios)})" if ratios else "n/a",
            f"{statistics.median(t99):.2f}" if t99 else "-",
            f"{_searching_pct(rs, 'polygon'):.1f} ({_searching_pct(rs, 'grid'):.1f})",
            f"{max(r['polygon']['step_ms']['p99'] for r in rs):.1f}",
        )
    console.print(table)
    console.print(
        f"search after coverage: {_searching_pct(runs, 'polygon'):.1f} % of the polygon planner's time, "
        f"{_searching_pct(runs, 'grid'):.1f} % of the grid's (flown after coverage came within "
        f"{FINAL_COVERAGE_TOLERANCE} of where the run ended)"
    )
    console.print(
        "time ratios: polygon / grid, only against grid runs that explored the map (complete, coverage"
        " >= 0.99, no collision); their count in brackets, n/a when there were none"
    )
    console.print(f"results: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
