# The two commands (README):  make demo   |   make test
# Each bootstraps its own virtual environment in .venv from a bare Python 3.11.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV := .venv
STAMP := $(VENV)/.installed-$(shell cksum pyproject.toml | cut -d' ' -f1)
BIN := $(VENV)/bin

.PHONY: setup bytecode demo test test-fast coverage lint wheel-smoke bench screenshots clean

# The packages are installed by uv (from PyPI, into the venv), byte-compiled at install.  The
# compiling matters: these machines and CI set PYTHONDONTWRITEBYTECODE=1, so Python never caches what
# it compiles on import, and every process recompiled every module it imported, every time: importing
# the service and the libraries it loads took 3.0 s of CPU against 1.1 s compiled, ITK with RTK 15.8 s
# against 10.4 s, and one `make test` starts some 160 Python processes (py-spy saw 164: robot links,
# services, CLIs).  On 2 idle cores, fresh clone: 12.6 s (22.6 s of CPU, once) against pip's 50 s
# (issue 42).
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet uv
	$(BIN)/uv pip install --quiet --compile-bytecode --python $(BIN)/python -e '.[test,cbct]'
	rm -f $(VENV)/.installed-*
	touch $(STAMP)

setup: $(STAMP)

# The checkout's own modules, compiled for the same reason (0.6 s; unchanged files are skipped, and
# Python checks each .pyc against its source's mtime and size before it uses one).
PACKAGES := registration drivers dicomnet service mocks benchmarks tests
bytecode: $(STAMP)
	$(BIN)/python -m compileall -q -j 0 $(PACKAGES)

demo: bytecode
	$(BIN)/oarmreg demo --out demo-output

# mypy settings (--strict for the five packages and the benchmarks, the pydantic plugin):
# pyproject.toml [tool.mypy].
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy registration drivers dicomnet service mocks benchmarks

# Build the wheel by docs/operations.md's install recipe, install it into a fresh venv in a temporary
# root, check the copied TOML, run simulate + detect from it (part of `make test` too).
wheel-smoke: $(STAMP)
	$(BIN)/python -m pytest -q -n 0 tests/integration/test_install_recipe.py

# Three workers on CI's two cores, each module on one of them (module-scoped services and the
# per-module leak guard stay whole); `PYTEST_WORKERS=0 make test` runs it in one process.  Three, not
# two: two workers kept the two cores only 128 % busy (services wait on sockets, pollers, robot
# moves) and, beside other load, got a smaller share of the CPU (issue #42: .ci/run with
# stress-ng --cpu 2 beside it, 12 min 51 s with two workers at load 6-11, 7 min 37 s with three at
# load mostly 5-7.5, 2.6-8.7).  The dearest modules start
# first (tests/helpers/module_costs.py orders them by tests/helpers/module_costs.json), so xdist's
# own reorder (by number of tests) is off: it left a few-but-slow module to run alone at the end.
PYTEST_WORKERS ?= 3
PYTEST_PARALLEL := $(if $(filter 0,$(PYTEST_WORKERS)),,-n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder)

test: lint bytecode
	$(BIN)/python -m pytest $(PYTEST_PARALLEL)

# The edit loop: lint, then every test but the simulator-driven accuracy ones (marker `slow`).
test-fast: lint bytecode
	$(BIN)/python -m pytest $(PYTEST_PARALLEL) -m "not slow"

# Line coverage of the five packages over the whole suite (not in .ci/run: the tracer is slow).
coverage: $(STAMP)
	$(BIN)/python -m pytest $(PYTEST_PARALLEL) -q --cov=registration --cov=drivers --cov=dicomnet --cov=service --cov=mocks --cov-report=term:skip-covered

bench: $(STAMP)
	$(BIN)/python -m benchmarks

# The status page and /docs in headless Chromium, written to docs/img/page-*.png (issue #21).
screenshots: $(STAMP)
	$(BIN)/python -m tests.browser.screenshots docs/img

clean:
	rm -rf $(VENV) demo-output .pytest_cache .mypy_cache .ruff_cache .hypothesis
