"""``make bench``'s script: its arguments are checked before any flight, and it keeps what it flew."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = [sys.executable, "benchmarks/run.py"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--seeds", "0"], "--seeds"),  # flew nothing and wrote an empty results file over the last one
        (["--maps", "nosuch"], "no such map in config/maps: nosuch"),  # likewise, silently
        (["--max-time", "0"], "--max-time"),
        (["--generated", "-2"], "--generated"),
    ],
)
def test_bad_arguments_are_refused_before_any_flight_and_nothing_is_written(
    tmp_path: Path, args: list[str], needle: str
) -> None:
    out = tmp_path / "r.json"
    run = subprocess.run([*SCRIPT, *args, "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and needle in run.stderr and "Traceback" not in run.stderr
    assert not out.exists()


def test_the_results_are_written_as_the_runs_go(tmp_path: Path) -> None:
    """A row per map and seed, with both planners' reports; the summary names the file."""
    out = tmp_path / "bench" / "r.json"
    cmd = [*SCRIPT, "--maps", "nook", "--seeds", "2", "--max-time", "3", "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    rows = json.loads(out.read_text())
    assert [(r["map"], r["seed"]) for r in rows] == [("nook", 1), ("nook", 2)]
    assert all(r["polygon"]["exploration_time_s"] <= 3.0 + 0.2 and r["grid"]["planner"] == "grid" for r in rows)
    assert not out.with_name("r.json.tmp").exists()
    assert str(out) in "".join(run.stdout.split())


def test_an_interrupted_bench_keeps_the_runs_it_flew(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Stopped during seed 2 (Ctrl-C, hours into ``make bench``), the file holds seed 1's row:
    the results used to be written only at the very end."""
    spec = importlib.util.spec_from_file_location("bench_run", "benchmarks/run.py")
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    real = bench.run_exploration

    def run_until_seed_2(*args: object, **kwargs: object) -> object:
        if kwargs["seed"] == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(bench, "run_exploration", run_until_seed_2)
    out = tmp_path / "r.json"
    monkeypatch.setattr(sys, "argv", ["run.py", "--maps", "nook", "--seeds", "3", "--max-time", "2", "--out", str(out)])
    with pytest.raises(KeyboardInterrupt):
        bench.main()
    assert [(r["map"], r["seed"]) for r in json.loads(out.read_text())] == [("nook", 1)]


STEP_SCRIPT = [sys.executable, "benchmarks/step_replay.py"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--rounds", "0"], "--rounds"),
        (["--maps", "nosuch"], "no such map in config/maps: nosuch"),
        (["--maps"], "--maps"),
        (["--baseline", "/nonexistent"], "is not a checkout of companion"),
    ],
)
def test_the_step_bench_refuses_bad_arguments_before_any_flight(tmp_path: Path, args: list[str], needle: str) -> None:
    out = tmp_path / "s.json"
    run = subprocess.run([*STEP_SCRIPT, *args, "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and needle in run.stderr and "Traceback" not in run.stderr
    assert not out.exists()


def test_the_step_bench_times_the_flights_own_steps_again(tmp_path: Path) -> None:
    """``make bench-step``: a row per map and seed, each replay the flight's very steps, and each
    step's least time over the replays summarised."""
    out = tmp_path / "s.json"
    cmd = [*STEP_SCRIPT, "--maps", "nook", "--rounds", "2", "--max-time", "8", "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    (row,) = json.loads(out.read_text())
    assert (row["map"], row["seed"], row["rounds"]) == ("nook", 1, 2)
    assert row["replay_same_setpoints"] is True
    assert row["steps"] == 81  # a frame every 0.1 s from 0 s to 8 s, both ends
    least = row["least_step_ms"]
    assert 0.0 < least["p50"] <= least["p99"] <= least["max"] and least["total"] >= least["max"]
    assert str(out) in "".join(run.stdout.split())


def test_the_step_bench_compares_with_a_baseline_on_the_same_steps(tmp_path: Path) -> None:
    """``--baseline DIR`` replays the same frames into that checkout's code, in turn with this
    tree's: against itself, the same answers, and the ratios of the two trees' least times."""
    out = tmp_path / "s.json"
    root = str(Path(__file__).resolve().parents[1])
    cmd = [*STEP_SCRIPT, "--maps", "nook", "--rounds", "2", "--max-time", "5", "--baseline", root, "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    (row,) = json.loads(out.read_text())
    assert row["replay_same_setpoints"] is True and row["baseline_same_setpoints"] is True
    assert row["baseline"] == root and row["baseline_least_step_ms"]["total"] > 0.0
    assert set(row["ratio_to_baseline"]) == {"total", "p50", "p99"}
    mine, theirs = row["least_step_ms"]["total"], row["baseline_least_step_ms"]["total"]
    assert row["ratio_to_baseline"]["total"] == pytest.approx(mine / theirs, rel=2e-3)
    assert "againstthebaseline" in "".join(run.stdout.split())  # rich wraps the line
