# LMDP Light Transport. The two commands: `make demo` and `make test` (see README.md).
#
#   make venv         .venv with CPython 3.11 and exactly the pinned packages (re-installs only when
#                     requirements*.txt change)
#   make test         fast test suite (engine + add-on); `make test-all` adds the slow ones
#   make demo         the whole pipeline on the built-in Cornell box, results in out/demo/
#   make extension    platform wheels into wheels/ and per-platform zips into dist/
#   make validate     Blender's own manifest validator
#   make bench        benchmarks (bench/run.py); `make bench-quick` is the short version
#   make clean        remove build outputs (keeps .venv); `make distclean` removes .venv too

SHELL := /bin/bash
PYTHON ?= python3.11
VENV ?= .venv
DIST ?= dist
WHEELS ?= wheels
PYTEST_ARGS ?=

PY := $(VENV)/bin/python
REQUIREMENTS := requirements.txt requirements-dev.txt
STAMP := $(VENV)/.requirements-stamp
# Blender's own extension tool, shipped inside the bpy wheel (expanded when a recipe runs).
BLENDER_EXT = $(firstword $(wildcard $(VENV)/lib/python3.11/site-packages/bpy/*/scripts/addons_core/bl_pkg/cli/blender_ext.py))

export PYTHON

.PHONY: venv check-env check-python test test-all demo extension wheels validate bench bench-quick clean distclean

check-env:
	@scripts/check_env.sh

check-python:
	@scripts/check_env.sh --no-libs

venv: $(STAMP)

$(STAMP): $(REQUIREMENTS) scripts/install_venv.sh scripts/pins.py | check-python
	@scripts/install_venv.sh $(VENV) requirements-dev.txt
	@touch $@

test: check-env venv
	$(PY) -m pytest tests $(PYTEST_ARGS)

test-all: check-env venv
	LMDP_SLOW_TESTS=1 $(PY) -m pytest tests $(PYTEST_ARGS)

demo: check-env venv
	BLENDER_USER_RESOURCES=$(CURDIR)/out/blender-user $(PY) scripts/lmdp_headless.py --demo cornell --output out/demo

wheels: check-python venv
	$(PY) scripts/fetch_wheels.py --manifest blender_manifest.toml --dest $(WHEELS)

extension: wheels
	@test -n "$(BLENDER_EXT)" || { echo "error: blender_ext.py not found in the bpy package of $(VENV)" >&2; exit 1; }
	rm -rf $(DIST) && mkdir -p $(DIST)
	$(PY) $(BLENDER_EXT) build --source-dir . --output-dir $(DIST) --split-platforms

validate: check-python venv
	@test -n "$(BLENDER_EXT)" || { echo "error: blender_ext.py not found in the bpy package of $(VENV)" >&2; exit 1; }
	$(PY) $(BLENDER_EXT) validate .

# Benchmarks write bench/results/<profile>/; the full run also regenerates docs/benchmarks.md,
# docs/images/bench_*.png and the README's benchmark block (see bench/run.py --help).
bench: check-env venv
	$(PY) bench/run.py

bench-quick: check-env venv
	$(PY) bench/run.py --quick

clean:
	rm -rf out $(DIST) $(WHEELS) .pytest_cache tests/.pytest_cache
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

distclean: clean
	rm -rf $(VENV)
