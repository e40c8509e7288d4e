# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
DEMO_DIR ?= demo-output
DEMO_TRIALS ?= 2
# `make real-data`: the README's real-recordings table (ETH Nano_Swarm_Mapping, exp2).
NANOSWARM ?= ../shared/datasets/eth_nano_swarm_mapping/exp2
REAL_DIR ?= real-output
REAL_TRIALS ?= 3
REAL_ESTIMATORS ?= icp_pf,beam_pf,likelihood_field_pf,gtsam_smoother
# How `make real-data` imports a flight: maps by the drones (leave-one-drone-out, or the
# flight beside a single drone's), and a scan the files cannot support (a corrupt row, a
# node without a pose) left out and reported at import rather than failing the flight.
# REAL_IMPORT="--map-from auto" refuses such a flight instead.
REAL_IMPORT ?= --map-from auto --bad-scans skip --missing-poses skip
# ... and a node whose sensors returned nothing set aside (named in table.md), not the flight.
REAL_EVALUATE ?= --set-aside-unusable
# `make real-data-drones`: a flight (REAL_DRONES_FLIGHT) as if flown by fewer of its drones.
REAL_DRONES_FLIGHT ?= four-drones
REAL_DRONE_SETS ?= 1,2,3 0,2,3 0,1,3 0,1,2 1,3 0,2
# The suite runs in TEST_WORKERS processes (pytest-xdist), one test file per worker at a
# time so that a file's module fixtures are built once; TEST_WORKERS=0 runs it in this process.
TEST_WORKERS ?= 2
PYTEST_WORKERS := $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

.PHONY: demo real-data real-data-drones test test-slow install syslibs clean

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

# Every flight folder of $(NANOSWARM) (a folder with scans.csv: exp2's four-drones and
# two-drones, or the flights of another experiment; or, one level deeper, EXP/FLIGHT: the
# flights of every experiment of a copy of the data set, named EXP-FLIGHT) imported once
# into $(REAL_DIR)/<flight> (kept: a rerun reuses the logs and evaluate's finished
# batches), then evaluated into $(REAL_DIR)/eval-<flight>, with REAL_IMPORT's options
# (above); every flight evaluated in one table, $(REAL_DIR)/compare-flights/comparison.md
# (tofloc plot). A flight that fails (a single drone with no flight beside it) is named and
# the others still run; make then fails.
real-data: install
	@flights=$$(cd "$(NANOSWARM)" 2>/dev/null && for d in */ */*/; do [ -f "$$d/scans.csv" ] && echo "$${d%/}"; done); \
	test -n "$$flights" || { \
	  echo "real-data: $(NANOSWARM) has no flight folder (a folder with scans.csv, such as four-drones/ or exp2/four-drones/; set NANOSWARM=...)"; exit 2; }; \
	failed=""; set --; IFS=$$(printf '\n_'); IFS=$${IFS%_}; \
	for f in $$flights; do \
	  n=$$(echo "$$f" | tr / -); \
	  if [ ! -d "$(REAL_DIR)/$$n/maps" ]; then \
	    $(VENV)/bin/tofloc import nanoswarm "$(NANOSWARM)/$$f" $(REAL_IMPORT) --out "$(REAL_DIR)/$$n" || { failed="$$failed $$f"; continue; }; fi; \
	  if $(VENV)/bin/tofloc evaluate "$(REAL_DIR)/$$n"/*.h5 --estimators $(REAL_ESTIMATORS) --trials $(REAL_TRIALS) \
	    $(REAL_EVALUATE) --out "$(REAL_DIR)/eval-$$n"; then set -- "$$@" "$(REAL_DIR)/eval-$$n/results.json"; else failed="$$failed $$f"; fi; \
	done; \
	[ $$# -eq 0 ] || $(VENV)/bin/tofloc plot "$$@" --out "$(REAL_DIR)/compare-flights" || failed="$$failed (compare-flights)"; \
	test -z "$$failed" || { echo "real-data: failed:$$failed (the others are in $(REAL_DIR))"; exit 1; }

# Each set of REAL_DRONE_SETS: the flight REAL_DRONES_FLIGHT imported with only those drones
# (--drones: their logs, maps from their scans alone) into $(REAL_DIR)/<flight>-d<set>, then
# evaluated into $(REAL_DIR)/eval-<flight>-d<set> (docs/real-data.md, "Fewer drones"); one
# comparison of every set (tofloc plot) in $(REAL_DIR)/compare-<flight>-subsets/comparison.md. Evaluated with
# REAL_EVALUATE's options, as `make real-data` is.
real-data-drones: install
	@test -f "$(NANOSWARM)/$(REAL_DRONES_FLIGHT)/scans.csv" || { \
	  echo "real-data-drones: $(NANOSWARM) has no $(REAL_DRONES_FLIGHT)/ flight folder (set NANOSWARM=... or REAL_DRONES_FLIGHT=...)"; exit 2; }
	@for s in $(REAL_DRONE_SETS); do \
	  d="$(REAL_DRONES_FLIGHT)-d$$(echo $$s | tr -d ,)"; \
	  if [ ! -d "$(REAL_DIR)/$$d/maps" ]; then \
	    $(VENV)/bin/tofloc import nanoswarm "$(NANOSWARM)/$(REAL_DRONES_FLIGHT)" --drones $$s --out "$(REAL_DIR)/$$d" || exit $$?; fi; \
	  $(VENV)/bin/tofloc evaluate "$(REAL_DIR)/$$d"/*.h5 --estimators $(REAL_ESTIMATORS) --trials $(REAL_TRIALS) \
	    $(REAL_EVALUATE) --out "$(REAL_DIR)/eval-$$d" || exit $$?; \
	  results="$$results $(REAL_DIR)/eval-$$d/results.json"; \
	done; \
	$(VENV)/bin/tofloc plot $$results --out "$(REAL_DIR)/compare-$(REAL_DRONES_FLIGHT)-subsets"

# `make test`: every test but those marked `slow` (under 10 minutes on 2 cores);
# `make test-slow`: those (a few minutes more). CI (.ci/run) runs both.
test: install
	$(PY) -m pytest -q $(PYTEST_WORKERS) -m "not slow"

test-slow: install
	$(PY) -m pytest -q $(PYTEST_WORKERS) -m slow

clean:
	rm -rf $(VENV) $(DEMO_DIR) $(REAL_DIR) .pytest_cache build *.egg-info
