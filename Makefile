# Everything runs from the project's own virtual environment in .venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATASET ?= synthetic
ARGS   ?=

EXTRAS := $(VENV)/.extras

.PHONY: install install-extras eval test test-fast report bench lint format clean-runs

install: $(STAMP)

# The model-backed segmenters' packages, for their tests on CPU (random weights).
# torchvision is pinned to torch 2.13.0's pair first so nothing upgrades torch; sam2 builds
# only without build isolation. SAM 3 is left out: its model needs CUDA (see README).
install-extras: $(EXTRAS)

$(EXTRAS): $(STAMP)
	$(BIN)/python -m pip install --quiet torchvision==0.28.0
	$(BIN)/python -m pip install --quiet -e '.[yolo]'
	$(BIN)/python -m pip install --quiet --no-build-isolation -e '.[sam2]'
	touch $(EXTRAS)

# CPU torch first (pinned: an unpinned torch pulls several GB of CUDA wheels), then the package.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev,launchers]'
	touch $(STAMP)

eval: install
	$(BIN)/python -m bench.eval dataset=$(DATASET) $(ARGS)

test: install install-extras
	$(BIN)/python -m pytest -q -m "not gpu" $(ARGS)

test-fast: install
	$(BIN)/python -m pytest -q -m "not slow and not gpu" $(ARGS)

report: install
	$(BIN)/python -m bench.report $(ARGS)

bench: install
	$(BIN)/python bench/bench_render.py $(ARGS)

lint: install
	$(BIN)/pre-commit run --all-files

format: install
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

clean-runs:
	rm -rf runs multirun outputs
