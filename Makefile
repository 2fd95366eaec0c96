# Every target creates .venv when it is missing and installs the project into it.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test lint format bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

# torch is pinned (CPU build from the machine's local wheel); reinstall when pyproject.toml changes.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install 'torch==2.13.0'
	$(BIN)/pip install -e '.[dev]'
	touch $(STAMP)

# Until the closed-loop demo exists: the three baselines on 100 generated scenarios.
run: $(STAMP)
	$(BIN)/tupa scenarios generate --n 100 --users 3 --seed 1 --out runs/demo/scenarios.json
	$(BIN)/tupa eval --policy min-distance --policy load-weighted --policy oracle \
		--scenarios runs/demo/scenarios.json --json runs/demo/eval.json

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

bench: $(STAMP)
	$(BIN)/python benchmarks/sim_speed.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
