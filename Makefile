# vistac: make setup | make demo | make test | make bench | make lint
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= out/demo
# Extra pip arguments for torch, e.g. TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu"
# where the default index would give a CUDA build.
TORCH_PIP_ARGS ?=
# The versions the tests and docs/results.md were measured with (`make lock` rewrites it).
CONSTRAINTS := constraints.txt
# System libraries the wheels need (open3d: libusb, libgomp, libGL).
SYSTEM_LIBS := libusb-1.0-0 libgomp1 libgl1

.PHONY: setup system-libs demo test test-all bench lint lock clean

setup: $(STAMP)

system-libs:
	@missing=""; for lib in libusb-1.0.so.0 libgomp.so.1 libGL.so.1; do \
	  ldconfig -p | grep -q "$$lib" || missing="$$missing $$lib"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system libraries for:$$missing"; \
	  if [ "$$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi; \
	  $$SUDO apt-get update -qq && $$SUDO apt-get install -y -qq $(SYSTEM_LIBS) >/dev/null; \
	fi

$(STAMP): pyproject.toml $(CONSTRAINTS) | system-libs
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade "pip>=23" "setuptools>=77" wheel
	# The CPU build of torch, pinned: an unpinned torch pulls gigabytes of CUDA packages.
	$(BIN)/pip install -q $(TORCH_PIP_ARGS) "torch==2.13.0"
	$(BIN)/pip install -q -c $(CONSTRAINTS) -e ".[dev]"
	touch $(STAMP)

# Look, fit the shape, then push until the belief converges (GNN trained by
# `vistac train skills/collect_pushes.yaml --preset ship`, on objects other than rect2).
demo: setup
	$(BIN)/vistac run skills/explore_push.yaml --out $(DEMO_OUT) --overwrite

test: setup
	$(BIN)/python -m pytest -q

test-all: setup
	$(BIN)/python -m pytest -q -m "slow or not slow"

# TRAIN_REPORTS="DIR/train.json ...": also report those trainings (time, trajectories).
bench: setup
	$(BIN)/python benchmarks/run_all.py --out BENCHMARKS.md $(TRAIN_REPORTS:%=--train-report %)

lint: setup
	$(BIN)/ruff check core plugins tests benchmarks examples
	$(BIN)/mypy core plugins

# After changing a dependency: pin what the set-up environment holds now (torch is pinned above).
lock:
	@test -x $(BIN)/pip || { echo "no $(VENV) to pin: run make setup first" >&2; exit 1; }
	set -o pipefail; { echo "# pip constraints for make setup: written by make lock"; \
	  $(BIN)/pip freeze --exclude-editable | grep -iv '^torch=='; } > $(CONSTRAINTS).new
	mv $(CONSTRAINTS).new $(CONSTRAINTS)

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache
