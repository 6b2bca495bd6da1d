# Everything runs from the project's own virtual environment in .venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATASET ?= synthetic
ARGS   ?=

EXTRAS := $(VENV)/.extras

# basic: one job after another (the first warms the shared stage cache; timings stay clean);
# local: parallel jobs on this machine (joblib); slurm: a cluster (submitit); slurm_local: the
# cluster code path (submitit) run on this machine.
LAUNCHER ?= basic
STAMPNOW := $(shell date +%Y-%m-%d_%H-%M-%S)
SWEEP     = $(BIN)/python -m bench.eval --multirun hydra/launcher=$(LAUNCHER) record=false \
            progress=false cache_dir=.cache/stages

.PHONY: install install-extras eval test test-fast report bench lint format clean-runs clean-cache \
        tables table-timing table-masks table-ablation table-robustness scenes

install: $(STAMP)

# The model-backed segmenters' packages, for their tests on CPU (random weights), gsplat,
# whose PyTorch reference functions check the CUDA backend's conventions on CPU, and Triton,
# whose interpreter runs the fused GPU vote kernel on the CPU in the tests.
# torchvision is pinned to torch 2.13.0's pair first so nothing upgrades torch; sam2 builds
# only without build isolation. SAM 3 is left out: its model needs CUDA (see README).
install-extras: $(EXTRAS)

$(EXTRAS): $(STAMP)
	$(BIN)/python -m pip install --quiet torchvision==0.28.0
	$(BIN)/python -m pip install --quiet -e '.[yolo]'
	$(BIN)/python -m pip install --quiet -e '.[gsplat]'
	$(BIN)/python -m pip install --quiet -e '.[triton]'
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

# CPU rows here; on a GPU machine `make bench ARGS="--devices cuda --out
# reports/bench_render_cuda.csv"` (with .[gsplat,triton] installed) gives the CUDA table.
bench: install
	$(BIN)/python bench/bench_render.py $(ARGS)
	$(BIN)/python bench/bench_contention.py

lint: install
	$(BIN)/pre-commit run --all-files

format: install
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

clean-runs:
	rm -rf runs multirun outputs

# The stage cache every run shares by default (.cache/stages): keyed by content, safe to empty.
clean-cache:
	rm -rf .cache/stages

# Fit the Gaussian scenes a dataset needs (2DGS; ARGS=fit.kind=3dgs for 3DGS).
SCENE ?=
scenes: install
	$(BIN)/python -m bench.scenes dataset=$(DATASET) $(if $(SCENE),scene=$(SCENE)) $(ARGS)

# The paper's tables, one target each (LAUNCHER=slurm runs the same sweep on a cluster).
table-timing: install
	$(BIN)/python -m bench.eval dataset=synthetic_360 segmenter=classical refine=student \
	  record=false progress=false hydra.run.dir=multirun/timing/$(STAMPNOW)/0 $(ARGS)
	$(BIN)/python -m bench.tables timing

table-masks: install
	$(SWEEP) dataset=synthetic_360_hd consensus.num_masks=1,3,6,12,25,50,100,null \
	  hydra.sweep.dir=multirun/masks/$(STAMPNOW) $(ARGS)
	$(BIN)/python -m bench.tables masks

table-ablation: install
	$(SWEEP) dataset=synthetic_360 segmenter=oracle_noisy consensus=rgc,flashsplat,weighted_mean \
	  hydra.sweep.dir=multirun/ablation/$(STAMPNOW)/methods $(ARGS)
	$(SWEEP) dataset=synthetic_360 segmenter=oracle_noisy consensus.eps=0.001,0.1,0.5 \
	  hydra.sweep.dir=multirun/ablation/$(STAMPNOW)/eps $(ARGS)
	$(SWEEP) dataset=synthetic_360 segmenter=oracle_noisy consensus.delta=0.5,1,4,8 \
	  hydra.sweep.dir=multirun/ablation/$(STAMPNOW)/delta $(ARGS)
	$(SWEEP) dataset=synthetic_360 segmenter=oracle_noisy consensus.min_votes=3,10 \
	  consensus.margin=0,0.5 hydra.sweep.dir=multirun/ablation/$(STAMPNOW)/votes $(ARGS)
	$(BIN)/python -m bench.tables ablation

table-robustness: install
	$(SWEEP) dataset=synthetic_360 segmenter=oracle segmenter.boundary_px=0,2,4 \
	  segmenter.flicker=0,0.1,0.3 hydra.sweep.dir=multirun/robustness/$(STAMPNOW) $(ARGS)
	$(BIN)/python -m bench.tables robustness

tables: table-timing table-masks table-ablation table-robustness
