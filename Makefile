# The two commands of the README: `make run` and `make test` (`make test-fast` in the edit loop, `make lint`).
# Each sets up the project's own virtual environment (.venv) on first use and reuses it afterwards
# (the stamp file records that the install for the current pyproject.toml finished).
PYTHON ?= python3
VENV ?= .venv
VENV_PYTHON := $(VENV)/bin/python
STAMP := $(VENV)/.installed
DATA ?= data
PORT ?= 3000
export QUADCORE_DATA_ROOT ?= $(abspath $(DATA))
# DAGSTER_HOME: <data root>/.dagster unless set (pipeline.run.instance), the demo's in its own root.

.PHONY: install run demo test test-fast lint docs ui bench fuzz cluster-up cluster-run cluster-down

install: $(STAMP)

$(VENV_PYTHON):
	$(PYTHON) -m venv $(VENV)

# torch first and pinned, so that nothing pulls a CUDA build (pip's configuration on these
# machines points at the on-disk CPU wheel).
$(STAMP): pyproject.toml | $(VENV_PYTHON)
	$(VENV_PYTHON) -m pip install --quiet --disable-pip-version-check torch==2.13.0
	$(VENV_PYTHON) -m pip install --quiet --disable-pip-version-check -e '.[dev]'
	touch $@

# The main job on the data root; on the default one (data/) while data/raw holds no logs, the demo
# in its own root data/demo (simulated flights never go into a raw folder of yours).
run: $(STAMP)
	$(VENV_PYTHON) -m pipeline

# The demo: six simulated flights with a hidden effect, in their own data root (data/demo).
demo: $(STAMP)
	$(VENV_PYTHON) -m pipeline --demo

# Both tiers on two pytest-xdist workers (the CI machine's two cores), the tests of a module
# together and the costliest groups first (tests/scheduling.py); XDIST= runs them in one process.
XDIST ?= -n 2 --dist loadscope --no-loadscope-reorder
test: $(STAMP)
	$(VENV_PYTHON) -m pytest -q $(XDIST) $(PYTEST_ARGS)

# The edit-loop tier: everything not marked slow (see pyproject's pytest markers).
test-fast: $(STAMP)
	$(VENV_PYTHON) -m pytest -q -m "not slow" $(XDIST) $(PYTEST_ARGS)

# lint-imports: the layer contracts of pyproject.toml's [tool.importlinter] (docs/architecture.md).
lint: $(STAMP)
	$(VENV_PYTHON) -m ruff check .
	$(VENV_PYTHON) -m mypy
	$(VENV)/bin/lint-imports --no-cache

# The documentation site (mkdocs.yml): the generated reference pages first (the CLI from its parser,
# the JSON keys from their pinned list), then mkdocs build --strict into site/: a broken link or
# anchor fails it. tests/test_docs.py builds it in the fast tier (CI: make test).
docs: $(STAMP)
	$(VENV_PYTHON) docs/gen_reference.py
	NO_MKDOCS_2_WARNING=1 $(VENV_PYTHON) -m mkdocs build --strict

# Dagster's UI and daemon until Ctrl-C / SIGTERM (plots served on the same port); PORT=3300 make ui for another port.
ui: $(STAMP)
	$(VENV_PYTHON) -m pipeline.run.ui --port $(PORT)

bench: $(STAMP)
	$(VENV_PYTHON) benchmarks/bench_export.py
	$(VENV_PYTHON) benchmarks/bench_pipeline.py
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_scale.py --per-flight 10 100 1000
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_scale.py --fleet 10 100 1000
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_diagnosis_memory.py 40 100 300 1000
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_scale.py 10 100
	$(VENV_PYTHON) benchmarks/bench_decode.py
	$(VENV_PYTHON) benchmarks/bench_physics.py
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_sufficient.py
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_summaries.py
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_profiles.py
	$(VENV_PYTHON) benchmarks/bench_learning.py
	$(VENV_PYTHON) benchmarks/bench_discover.py
	$(VENV_PYTHON) benchmarks/bench_export_c.py
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_power.py
	nice -n 10 $(VENV_PYTHON) benchmarks/bench_timing_calibration.py

# The fuzz harness (tests/fuzz): 2,000 mutants of the real logs (simulated ones where absent), the
# structure-aware cases of tests/fuzz/structure.py, 100 writers and 8 main jobs killed at random moments;
# and the config harness (tests/fuzz/configs.py: 130 hostile vehicle and model files, outputs edited to
# name code, a decoy tree of user files around the output folders). Prints the counts docs/benchmarks.md
# (Robustness) quotes.
fuzz: $(STAMP)
	nice -n 10 $(VENV_PYTHON) -m tests.fuzz.harness --mutants 2000 --kills 100 --pipeline-kills 8
	nice -n 10 $(VENV_PYTHON) -m tests.fuzz.configs

# The local cluster (pipeline.cluster, deploy/local): PostgreSQL, Redis, an S3 store (moto), Celery
# workers, the daemon and the webserver, all on 127.0.0.1, state in .cluster/. WORKERS=4 for more.
WORKERS ?= 2
cluster-up: $(STAMP)
	bash deploy/local/system-packages.sh
	$(VENV_PYTHON) -m pipeline.cluster up --workers $(WORKERS)

# The main job with its runs on the cluster (through the daemon's queue, steps on the workers).
cluster-run: $(STAMP)
	$(VENV_PYTHON) -m pipeline.cluster run

cluster-down: $(STAMP)
	$(VENV_PYTHON) -m pipeline.cluster down
