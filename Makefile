# Every target creates .venv when it is missing and installs the project into it.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test test-fast lint format bench clean browser llvm test-containers

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

# torch is pinned (CPU build from the machine's local wheel); reinstall when pyproject.toml changes.
# The ray extra is installed so that the tests of tupa sweep --backend ray run (they skip without).
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/pip install 'torch==2.13.0'
	$(BIN)/pip install -e '.[dev,ray]'
	touch $(STAMP)

# The closed loop over a real district (the shipped ray-traced site munich): sitl-mock +
# tupa serve (default policy) + the simulated network controller.
run: $(STAMP)
	$(BIN)/tupa demo --environment site:munich --out runs/demo

# The operator view's browser test (tests/e2e/test_operator_view.py) drives Debian's chromium
# through Playwright (a dev extra; Playwright's own browser download is not reachable here).
# Installed when missing and we are root on Debian; otherwise the test says why it skips, and
# fails under CI.
browser:
	@command -v chromium >/dev/null 2>&1 || \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y chromium) || \
	      { echo "chromium: the install failed"; [ -z "$$CI" ]; }; \
	  else \
	    echo "chromium is missing (apt-get install chromium): the browser test will skip"; \
	  fi

# Sionna RT (the sites extra, tupa[sites]) ray-traces on the CPU through Dr.Jit's LLVM backend,
# which needs Debian's libllvm19 (the system's default LLVM is too old): installed when missing
# and we are root on Debian, as chromium is (sim/sites/raytrace.py finds it). Without the extra,
# the site build's test skips and says why.
llvm:
	@ls /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1 || \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    (apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y libllvm19) || \
	      { echo "libllvm19: the install failed"; [ -z "$$CI" ]; }; \
	  else \
	    echo "libllvm19 is missing (apt-get install libllvm19): a site build cannot ray-trace"; \
	  fi

# The tests run in parallel (pytest-xdist): TEST_WORKERS processes (default: three for every two
# cores, at least one: the suite mostly waits; docs/results.md has the runs), and
# --dist loadgroup keeps each xdist_group on one worker, one test after another (the timing
# tests, the Ray tests, the tests of one ns-3 worker or one module-wide server: tests/tiers.py).
# A timing test (they assert latencies under load) starts once the tests already running have
# ended and runs beside at most one other (tests/machine_room.py). pytest-randomly shuffles the
# order and prints its seed: PYTEST_ADDOPTS=--randomly-seed=N gives the same order again (which
# worker runs which test can still differ; TEST_WORKERS=0 runs them all in one process).
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 2); echo $$(( n * 3 / 2 > 0 ? n * 3 / 2 : 1 )))
PYTEST := $(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadgroup

# Everything: every tier (tests/tiers.py), as CI runs it (.ci/run); the 25 slowest tests are
# listed at the end (where the suite's time goes).
test: $(STAMP) browser llvm
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(PYTEST) --durations=25

# The inner loop: lint, then the tests that need no process, flying mock, training, ns-3,
# browser or Ray (pure logic, in process: pytest --fast, tests/conftest.py).
test-fast: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(PYTEST) --fast

# The containers, built and run for real (not part of make test; .ci/run runs it after): the
# image from the offline base (scripts/build_image.sh's steps, layers cached between runs), the
# compose stack up, healthy and flying, a restart without re-arming, the teardown, the fleet and
# trainer profiles (tests_containers/, in file order). Needs a Docker daemon with the Compose v2
# plugin: scripts/install_docker.sh installs them (root, Debian), scripts/with_dockerd.sh starts
# a daemon for the command when none runs. Writes benchmarks/results/containers.json.
test-containers: $(STAMP)
	$(BIN)/python -m pytest tests_containers -p no:randomly -o timeout=1800 -v

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

bench: $(STAMP)
	$(BIN)/python benchmarks/sim_speed.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache sim/__pycache__/numba-*
