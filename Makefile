# The two commands of the README: `make run` and `make test` (`make test-fast` in the edit loop, `make lint`).
PYTHON ?= python3
DATA ?= data
export QUADCORE_DATA_ROOT ?= $(abspath $(DATA))
export DAGSTER_HOME ?= $(QUADCORE_DATA_ROOT)/.dagster

.PHONY: install run test test-fast lint ui bench

install:
	$(PYTHON) -m pip install --quiet --disable-pip-version-check torch==2.13.0
	$(PYTHON) -m pip install --quiet --disable-pip-version-check -e '.[dev]'

run: install
	$(PYTHON) -m pipeline

test:
	$(PYTHON) -m pytest -q

# The edit-loop tier: everything not marked slow (see pyproject's pytest markers).
test-fast:
	$(PYTHON) -m pytest -q -m "not slow"

lint:
	$(PYTHON) -m ruff check .
	$(PYTHON) -m mypy

ui:
	mkdir -p $(DAGSTER_HOME)
	dagster dev -w workspace.yaml -h 127.0.0.1 -p 3000

bench:
	$(PYTHON) benchmarks/bench_decode.py
	$(PYTHON) benchmarks/bench_physics.py
	$(PYTHON) benchmarks/bench_learning.py
	$(PYTHON) benchmarks/bench_discover.py
