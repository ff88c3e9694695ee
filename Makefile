# The two commands a newcomer runs: `make demo` and `make test`. Both do all set-up first.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
SHELL  := /bin/bash

.PHONY: setup demo test eval bench lint format clean system-deps

setup: $(STAMP)

# open3d loads libusb-1.0 at import time; install it when missing (root), else say how.
system-deps:
	@if ! /sbin/ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "installing libusb-1.0-0 (needed by open3d)"; \
	    (apt-get install -y -qq libusb-1.0-0 >/dev/null 2>&1 || \
	     (apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null)); \
	  else \
	    echo "open3d needs libusb-1.0-0: run  sudo apt-get install -y libusb-1.0-0"; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml | system-deps
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	# TrackEval (HOTA in wm.evaluation) without its declared opencv-python, which would
	# replace opencv-python-headless; HOTA uses numpy and scipy only
	$(PY) -m pip install -q --no-deps 'trackeval==1.3.0'
	@touch $(STAMP)

# The main job on the embedded default scenario.
demo: setup system-deps
	$(VENV)/bin/wm demo

# The whole test suite (slow evaluations excluded: see `make eval`).
test: setup system-deps
	$(PY) -m pytest -q -n 2 -m "not eval"

# Slow evaluations against ground truth; each figure lands in results/*.json.
eval: setup system-deps
	$(PY) -m pytest -q -m eval

# Benchmarks: ratios against baselines run side by side; each figure lands in results/*.json.
bench: setup system-deps
	$(PY) -m bench

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: setup
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

clean:
	rm -rf $(VENV) results out .pytest_cache .ruff_cache *.egg-info
