# asgp_ros: `make demo` and `make test` set everything up on a fresh machine.
PYTHON ?= python3
VENV   := .venv
VPY    := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
SYSSTAMP := $(VENV)/.system-deps

.PHONY: setup test demo firmware bench lint clean

setup: $(STAMP) $(SYSSTAMP)

# Debian packages: the AVR toolchain for the firmware, simavr to run it, libfaketime (tests).
$(SYSSTAMP): scripts/install-system-deps.sh | $(STAMP)
	bash scripts/install-system-deps.sh
	touch $@

$(STAMP): setup.py package.xml
	test -x $(VPY) || $(PYTHON) -m venv $(VENV)
	$(VPY) -m pip install --quiet --upgrade pip wheel setuptools
	$(VPY) -m pip install --quiet -e '.[ros,test]'
	touch $@

# Two workers (pytest-xdist): the suite is mostly waiting on subprocesses and DDS.
test: setup
	$(VPY) -m pytest test -n 2 --dist worksteal

# The demo needs the Python environment only (no AVR toolchain). --force: a second
# `make demo` replaces the first one's demo-output/ (and nothing that is not a demo's).
# The predictor adapts online, its variance scale included (README, the top).
demo: $(STAMP)
	$(VENV)/bin/asgp demo --force

firmware: $(SYSSTAMP)
	$(MAKE) -C firmware

# Three benchmarks read a dataset (`asgp dataset --out DIR --scale 1 --seed 0`): given with
# `make bench DATA=DIR`, else skipped with a line saying so. echo_node.py is no benchmark:
# the reference node predictor_latency.py starts and stops (alone it runs until stopped).
DATA ?=
DATA_BENCH := benchmarks/adapt_choice.py benchmarks/calibration_covariates.py \
	benchmarks/calibration_regimes.py
NOT_BENCH := benchmarks/echo_node.py
BENCH_RUN ?= $(VPY)

bench: setup
	@for b in benchmarks/*.py; do \
	  args=""; \
	  case " $(NOT_BENCH) " in *" $$b "*) continue;; esac; \
	  case " $(DATA_BENCH) " in *" $$b "*) \
	    if [ -z "$(DATA)" ]; then echo "== $$b: skipped (needs a dataset: make bench DATA=DIR)"; \
	      continue; fi; \
	    if [ "$$b" = benchmarks/calibration_regimes.py ]; then \
	      args="docs/reproduction/models/tile_asgp.npz $(DATA)/tile/tile_07 $(DATA)/tile/tile_08"; \
	    else args="$(DATA)"; fi;; \
	  esac; \
	  echo "== $$b $$args"; $(BENCH_RUN) $$b $$args || exit 1; \
	done

lint: setup
	$(VPY) -m ruff check asgp_ros test benchmarks launch
	$(VPY) -m mypy --strict asgp_ros

clean:
	rm -rf $(VENV) build install log .pytest_cache .mypy_cache .ruff_cache
