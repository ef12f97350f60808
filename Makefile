# Two commands set everything up on a fresh machine:
#   make demo       - create .venv, install, replay the bundled default insertion headless
#   make test       - same environment, run the whole test suite
#   make test-fast  - every test but the slow ones and the real-time ones, while editing
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast bench bench-cohort clean

$(STAMP): pyproject.toml
	@echo "installing haptic-acu and its dependencies into $(VENV) (a minute or two)..."
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	$(PY) -m haptic_acu.cli.precompile  # numba's kernels and the net tables, cached now, not on the first demo
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/haptic-acu replay

# Every test: those that measure nothing in real time two at a time (pytest-xdist), then the real-time
# ones (marked serial in tests/conftest.py) alone; one closing line counts both runs. The parallel run
# hands out whole modules, longest first (tests/conftest.py orders them; xdist's own reordering off).
XDIST := -n 2 --dist loadfile --no-loadscope-reorder
# Python caches compiled bytecode (and pytest its rewritten test modules) even where the environment
# says not to: every test process imports the whole package, and compiling it again each time costs
# seconds per process.
unexport PYTHONDONTWRITEBYTECODE
test: $(STAMP)
	@mkdir -p runs
	@rm -f runs/junit-*.xml
	-$(PY) -m pytest -q $(XDIST) -m "not serial" --junitxml=runs/junit-parallel.xml
	-$(PY) -m pytest -q -m serial --junitxml=runs/junit-serial.xml
	@$(PY) tools/test_summary.py runs/junit-parallel.xml runs/junit-serial.xml

test-fast: $(STAMP)
	$(PY) -m pytest -q $(XDIST) -m "not slow and not serial"

# the full benchmark, with pyshtools for the SH comparison rows; docs/performance.md rendered from its JSON
bench: $(STAMP)
	$(PY) -m pip install -q -e '.[bench]'
	@mkdir -p runs
	$(VENV)/bin/haptic-acu bench --json runs/bench.json --overwrite
	$(PY) tools/perf_page.py runs/bench.json --out docs/performance.md  # the page's figures, from that JSON

# the cohort benchmark: 200 synthetic one-minute sessions, local pool and a Dask LocalCluster
# (local, Dask, local again: about 6 minutes on two quiet cores; `make bench` measures only 8 ten-second sessions)
bench-cohort: $(STAMP)
	@mkdir -p runs
	f=runs/bench-cohort-$$(date -u +%Y%m%dT%H%M%SZ).json; \
	$(PY) -m haptic_acu.bench.cohort_bench --sessions 200 --duration 60 > $$f && cat $$f

clean:
	rm -rf $(VENV) runs .pytest_cache
