"""Step-time benchmark without the flight's noise: fly each map once (polygon planner, in-process
simulator, the thesis's drift), record every frame the product was given, then replay those
frames into fresh explorers ``--rounds`` times with no simulator, and keep each step's least time.

A flight's own step times move by 10-50 % from run to run on a shared machine (other work, the
clock's speed), which hides changes of a few per cent. The explorer is deterministic, so each
replay is the flight's very steps (checked: every setpoint must be the flight's), and a step's
least time over a few replays is what it costs on this machine. Writes JSON and prints a table.

    .venv/bin/python benchmarks/step_replay.py --out out/bench/step.json [--maps room apartment]
        [--seeds 1] [--rounds 5]
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.argtypes import number
from sitl.runner import PolygonPolicy, replay, run_exploration
from sitl.world import load_world

DEFAULT_MAPS = ("room", "apartment", "lshape")


def _figures(times_ms: np.ndarray) -> dict[str, float]:
    return {
        "p50": round(float(np.percentile(times_ms, 50)), 3),
        "p99": round(float(np.percentile(times_ms, 99)), 3),
        "max": round(float(times_ms.max()), 3),
        "total": round(float(times_ms.sum()), 1),
    }


def measure(path: Path, seed: int, rounds: int, max_time_s: float) -> dict[str, Any]:
    """One map and seed: the flight's report and its step figures, and the replays' least times."""
    trace = run_exploration(load_world(path), "polygon", seed=seed, max_time_s=max_time_s, record_frames=True)
    if not isinstance(trace.policy, PolygonPolicy) or trace.policy.recorded is None:
        raise RuntimeError("the polygon flight kept no frames")
    recorded = trace.policy.recorded
    least = np.full(len(recorded), np.inf)
    same = True
    for _ in range(rounds):
        gc.collect()  # each replay starts from the same heap, not the last one's garbage
        times_ms, same_setpoints = replay(recorded)
        same = same and same_setpoints
        least = np.minimum(least, times_ms)
    report = trace.report
    return {
        "map": path.stem,
        "seed": seed,
        "termination": report["termination"],
        "exploration_time_s": report["exploration_time_s"],
        "steps": len(recorded),
        "rounds": rounds,
        "replay_same_setpoints": same,
        "flight_step_ms": _figures(np.asarray(trace.policy.step_ms)),
        "least_step_ms": _figures(least),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/bench/step.json"))
    parser.add_argument("--maps", nargs="*", default=list(DEFAULT_MAPS), help="map names in config/maps")
    parser.add_argument("--seeds", type=number(int, 1), default=1)
    parser.add_argument("--rounds", type=number(int, 1), default=5, help="replays of each flight")
    parser.add_argument("--max-time", type=number(float, above_low=True), default=3600.0)
    args = parser.parse_args()
    paths = {p.stem: p for p in Path("config/maps").glob("*.geojson")}
    unknown = sorted(set(args.maps) - set(paths))
    if unknown or not args.maps:
        parser.error(f"no such map in config/maps: {', '.join(unknown)}" if unknown else "--maps names none")
    try:
        args.out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parser.error(f"cannot create {args.out.parent}: {err.strerror or err}")
    console = Console()
    rows: list[dict[str, Any]] = []
    for name in args.maps:
        for seed in range(1, args.seeds + 1):
            t0 = time.perf_counter()
            row = measure(paths[name], seed, args.rounds, args.max_time)
            row["wall_s"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            tmp = args.out.with_name(args.out.name + ".tmp")
            tmp.write_text(json.dumps(rows, indent=2) + "\n")
            tmp.replace(args.out)  # after every map: an interrupted bench keeps what it measured
            least = row["least_step_ms"]
            console.print(
                f"{name} seed {seed}: {row['steps']} steps, least of {args.rounds}: "
                f"p50 {least['p50']:.2f} ms, p99 {least['p99']:.2f} ms ({row['wall_s']:.0f} s)"
            )
    table = Table(title=f"map + planner step, each step's least time over {args.rounds} replays [ms]")
    for col in ("map", "seed", "steps", "p50", "p99", "max", "all steps [s]", "flight's own p50 / p99", "replay"):
        table.add_column(col)
    for row in rows:
        least, flight = row["least_step_ms"], row["flight_step_ms"]
        table.add_row(
            row["map"],
            str(row["seed"]),
            str(row["steps"]),
            f"{least['p50']:.2f}",
            f"{least['p99']:.2f}",
            f"{least['max']:.1f}",
            f"{least['total'] / 1e3:.2f}",
            f"{flight['p50']:.2f} / {flight['p99']:.2f}",
            "same steps" if row["replay_same_setpoints"] else "[red]DIFFERENT SETPOINTS[/red]",
        )
    console.print(table)
    console.print(f"results: {args.out}")
    return 0 if all(r["replay_same_setpoints"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
