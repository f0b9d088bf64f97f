# The two commands a new user runs: `make demo` and `make test`. Both create .venv when missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench bench-step clean venv

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip==24.3.1 setuptools==75.6.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/companion sim --map config/maps/room.geojson --seed 1 --report out/demo/report.json --plots out/demo

test: $(STAMP)
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check companion sitl tests benchmarks
	$(BIN)/ruff format --check companion sitl tests benchmarks
	$(BIN)/mypy --strict companion/core

bench: $(STAMP)
	$(BIN)/python benchmarks/step_replay.py --out out/bench/step.json
	$(BIN)/python benchmarks/run.py --out out/bench/results.json --generated 10

# The step's cost alone (minutes): three flights replayed, each step's least time of five.
bench-step: $(STAMP)
	$(BIN)/python benchmarks/step_replay.py --out out/bench/step.json

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache
