# Quick start: `make sim` flies the default simulated flight; `make test` runs the test suite.
PY ?= python3
VENV := .venv
STAMP := $(VENV)/.installed

.PHONY: sim test lint bench clean missionplanner-plugin

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install --quiet --upgrade pip
	$(VENV)/bin/python -m pip install --quiet -e '.[dev]'
	# MAVProxy for the ground-station module: without its deps (they pull the non-headless OpenCV)
	$(VENV)/bin/python -m pip install --quiet --no-deps MAVProxy pyserial
	touch $(STAMP)

sim: $(STAMP)
	$(VENV)/bin/gsoe sim --out out/sim --overwrite

# two workers (pytest-xdist), one test file each at a time, in the order tests/conftest.py gives (the long files
# first): the SIL tests wait on real time while the other core
# computes; TEST_WORKERS=0 runs them in one process
TEST_WORKERS ?= 2
test: $(STAMP)
	$(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

lint: $(STAMP)
	$(VENV)/bin/ruff check common gsoe fusion pipeline nav sim cli tests
	$(VENV)/bin/mypy common gsoe fusion pipeline sim nav cli

bench: $(STAMP)
	$(VENV)/bin/gsoe bench

# the Mission Planner plugin's single file, made from gcs/missionplanner/src/ (Python's standard library only)
missionplanner-plugin:
	$(PY) gcs/missionplanner/build.py release

clean:
	rm -rf $(VENV) out
