# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_DIR ?= demo-output
DEMO_TRIALS ?= 2
# The suite runs in TEST_WORKERS processes (pytest-xdist), one test file per worker at a
# time so that a file's module fixtures are built once; TEST_WORKERS=0 runs it in this process.
TEST_WORKERS ?= 2
PYTEST_WORKERS := $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

.PHONY: demo test test-fast install syslibs clean

# Open3D links against libusb-1.0 (Debian/Ubuntu package libusb-1.0-0).
syslibs:
	@sh scripts/ensure-libusb.sh

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[test]"
	@touch $(STAMP)

install: syslibs $(STAMP)

demo: install
	$(VENV)/bin/tofloc paper --estimators $$($(VENV)/bin/python -c 'from tofloc.registry import ESTIMATORS; print(",".join(ESTIMATORS.names()))') --trials $(DEMO_TRIALS) --out $(DEMO_DIR)

test: install
	$(PY) -m pytest -q $(PYTEST_WORKERS)

test-fast: install
	$(PY) -m pytest -q $(PYTEST_WORKERS) -m "not slow"

clean:
	rm -rf $(VENV) $(DEMO_DIR) .pytest_cache build *.egg-info
