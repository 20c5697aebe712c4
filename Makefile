# The two commands of the README: `make run` and `make test`.
PYTHON ?= python3
DATA ?= data
export QUADCORE_DATA_ROOT ?= $(abspath $(DATA))
export DAGSTER_HOME ?= $(QUADCORE_DATA_ROOT)/.dagster

.PHONY: install run test ui bench

install:
	$(PYTHON) -m pip install --quiet --disable-pip-version-check torch==2.13.0
	$(PYTHON) -m pip install --quiet --disable-pip-version-check -e '.[dev]'

run: install
	$(PYTHON) -m pipeline

test:
	$(PYTHON) -m pytest -q

ui:
	mkdir -p $(DAGSTER_HOME)
	dagster dev -w workspace.yaml -h 127.0.0.1 -p 3000

bench:
	$(PYTHON) benchmarks/bench_decode.py
	$(PYTHON) benchmarks/bench_physics.py
	$(PYTHON) benchmarks/bench_learning.py
	$(PYTHON) benchmarks/bench_discover.py
