"""Step-time benchmark without the flight's noise: fly each map once (polygon planner, in-process
simulator, the thesis's drift), record every frame the product was given, then replay those
frames into fresh explorers ``--rounds`` times with no simulator, and keep each step's least time.

A flight's own step times move by 10-50 % from run to run on a shared machine (other work, the
clock's speed), which hides changes of a few per cent. The explorer is deterministic, so each
replay is the flight's very steps (checked: every setpoint must be the flight's), and a step's
least time over a few replays is what it costs on this machine. Writes JSON and prints a table.

    .venv/bin/python benchmarks/step_replay.py --out out/bench/step.json [--maps room apartment]
        [--seeds 1] [--rounds 5] [--baseline DIR]

``--baseline DIR`` (another checkout, say of the last release) also replays the same frames into
that code, each round in two fresh processes taking turns (this tree's and the baseline's), and
gives the ratios this / baseline: a step change of a few per cent, measured on the same steps at
the same time. The machine's speed drifts through the day even in least times; ratios of trees
replayed in turn do not.
"""

from __future__ import annotations

import argparse
import gc
import json
import pickle
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from companion.argtypes import number
from sitl.replay import RecordedStep, replay
from sitl.runner import PolygonPolicy, run_exploration
from sitl.world import load_world

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_MAPS = ("room", "apartment", "lshape")
# Run in a fresh process: sitl/replay.py loaded by path, against the companion of the tree given.
_REPLAY_IN_TREE = """
import importlib.util, json, pickle, sys
tree, module, frames = sys.argv[1:4]
sys.path.insert(0, tree)
spec = importlib.util.spec_from_file_location("_replay", module)
replay = importlib.util.module_from_spec(spec)
spec.loader.exec_module(replay)
with open(frames, "rb") as f:
    times_ms, same = replay.replay(pickle.load(f))
print(json.dumps([same, times_ms]))
"""


def _figures(times_ms: np.ndarray) -> dict[str, float]:
    return {
        "p50": round(float(np.percentile(times_ms, 50)), 3),
        "p99": round(float(np.percentile(times_ms, 99)), 3),
        "max": round(float(times_ms.max()), 3),
        "total": round(float(times_ms.sum()), 1),
    }


def _replay_in(tree: Path, frames_file: Path) -> tuple[list[float], bool]:
    """:func:`sitl.replay.replay` of the pickled steps in a fresh process, against ``tree``'s code."""
    run = subprocess.run(
        [sys.executable, "-c", _REPLAY_IN_TREE, str(tree), str(ROOT / "sitl" / "replay.py"), str(frames_file)],
        capture_output=True,
        text=True,
        check=False,
    )
    if run.returncode != 0:
        raise RuntimeError(f"replay in {tree} failed: {run.stderr.strip().splitlines()[-1:]}")
    same, times_ms = json.loads(run.stdout.strip().splitlines()[-1])
    return times_ms, bool(same)


def _least(replays: list[tuple[list[float], bool]]) -> tuple[np.ndarray, bool]:
    """Each step's least time over the replays, and whether every replay answered as the flight."""
    return np.min(np.array([t for t, _ in replays]), axis=0), all(same for _, same in replays)


def _ratios(mine: np.ndarray, base: np.ndarray) -> dict[str, float]:
    return {
        "total": round(float(mine.sum() / base.sum()), 4),
        "p50": round(float(np.percentile(mine, 50) / np.percentile(base, 50)), 4),
        "p99": round(float(np.percentile(mine, 99) / np.percentile(base, 99)), 4),
    }


def measure(path: Path, seed: int, rounds: int, max_time_s: float, baseline: Path | None = None) -> dict[str, Any]:
    """One map and seed: the flight's report and its step figures, and the replays' least times
    (and the baseline's, replayed in turn with this tree's, each in a fresh process)."""
    trace = run_exploration(load_world(path), "polygon", seed=seed, max_time_s=max_time_s, record_frames=True)
    if not isinstance(trace.policy, PolygonPolicy) or trace.policy.recorded is None:
        raise RuntimeError("the polygon flight kept no frames")
    recorded: list[RecordedStep] = trace.policy.recorded
    mine: list[tuple[list[float], bool]] = []
    theirs: list[tuple[list[float], bool]] = []
    if baseline is None:
        for _ in range(rounds):
            gc.collect()  # each replay starts from the same heap, not the last one's garbage
            mine.append(replay(recorded))
    else:
        with tempfile.TemporaryDirectory() as tmp:
            frames_file = Path(tmp) / "frames.pickle"
            frames_file.write_bytes(pickle.dumps(recorded))
            for k in range(rounds):  # taking turns, each first in every other round
                for tree, out in ((ROOT, mine), (baseline, theirs))[:: 1 if k % 2 == 0 else -1]:
                    out.append(_replay_in(tree, frames_file))
    least, same = _least(mine)
    report = trace.report
    row: dict[str, Any] = {
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
    if baseline is not None:
        base, base_same = _least(theirs)
        row["baseline"] = str(baseline)
        row["baseline_same_setpoints"] = base_same  # False: the baseline flies differently
        row["baseline_least_step_ms"] = _figures(base)
        row["ratio_to_baseline"] = _ratios(least, base)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=Path("out/bench/step.json"))
    parser.add_argument("--maps", nargs="*", default=list(DEFAULT_MAPS), help="map names in config/maps")
    parser.add_argument("--seeds", type=number(int, 1), default=1)
    parser.add_argument("--rounds", type=number(int, 1), default=5, help="replays of each flight")
    parser.add_argument("--max-time", type=number(float, above_low=True), default=3600.0)
    parser.add_argument("--baseline", type=Path, default=None, help="another checkout to compare with")
    args = parser.parse_args()
    if args.baseline is not None and not (args.baseline / "companion" / "core" / "explorer.py").is_file():
        parser.error(f"--baseline {args.baseline} is not a checkout of companion (no companion/core/explorer.py)")
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
            row = measure(paths[name], seed, args.rounds, args.max_time, args.baseline)
            row["wall_s"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            tmp = args.out.with_name(args.out.name + ".tmp")
            tmp.write_text(json.dumps(rows, indent=2) + "\n")
            tmp.replace(args.out)  # after every map: an interrupted bench keeps what it measured
            least = row["least_step_ms"]
            against = ""
            if "ratio_to_baseline" in row:
                r = row["ratio_to_baseline"]
                against = (
                    f"; against the baseline: all steps x{r['total']:.3f}, p50 x{r['p50']:.3f}, p99 x{r['p99']:.3f}"
                )
                if not row["baseline_same_setpoints"]:
                    against += " [yellow](the baseline flies differently: other steps)[/yellow]"
            console.print(
                f"{name} seed {seed}: {row['steps']} steps, least of {args.rounds}: "
                f"p50 {least['p50']:.2f} ms, p99 {least['p99']:.2f} ms ({row['wall_s']:.0f} s){against}"
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
