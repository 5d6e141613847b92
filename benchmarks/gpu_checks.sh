#!/usr/bin/env bash
# Every GPU check of lerobot-pdp in one run: the CUDA tests, new-chunk latency (with a kernel profile and the
# compiled variants), lerobot-train rates of PDP and LeRobot diffusion at two batch sizes on the GPU and on the
# machine's CPU, and the in-process training steps with and without a camera. Each step has a time cap, so that
# a run with a deadline (a machine lent for minutes) ends with whatever it measured; results go to OUT_DIR
# (JSON lines, logs, summary.txt), the figures docs/performance.md ("On a GPU") reports.
#
#   bash benchmarks/gpu_checks.sh OUT_DIR [DEADLINE_S]      # default deadline 1500 s
#   STEPS="tests select train cameras cpu" bash benchmarks/gpu_checks.sh OUT_DIR   # a subset, in that order
#   TRAIN_BATCHES="256" CAMERA_BATCHES="64" ...                                  # batch sizes (default 64 256)
#
# Run from the repository root, in an environment where `import lerobot_pdp` and `lerobot-train` work and
# torch sees a GPU. USE_FLAX=0 USE_TF=0 keep diffusers from importing JAX/TensorFlow (~20 s per process).
set -o pipefail
OUT=${1:?usage: gpu_checks.sh OUT_DIR [DEADLINE_S]}
DL=${2:-1500}
STEPS=${STEPS:-"select train tests cameras cpu"}
TRAIN_BATCHES=${TRAIN_BATCHES:-"64 256"}
CAMERA_BATCHES=${CAMERA_BATCHES:-"64 256"}
PY=${PYTHON:-python3}
export USE_FLAX=0 USE_TF=0 PYTHONUNBUFFERED=1 HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 TQDM_DISABLE=1
mkdir -p "$OUT/logs"
S=$OUT/summary.txt
T0=$(date +%s)
el() { echo $(( $(date +%s) - T0 )); }
log() { echo "[$(el)s] $*" | tee -a "$S"; }
# seconds a step may take: its own cap, or what is left before the deadline (minus a reserve)
cap() { local left=$(( DL - $(el) - 10 )); [ "$left" -lt "$1" ] && echo "$left" || echo "$1"; }
runs() { [[ " $STEPS " == *" $1 "* ]]; }

log "start $(date -u +%FT%TZ), commit $(git rev-parse --short HEAD 2>/dev/null), steps: $STEPS (train B=$TRAIN_BATCHES, cameras B=$CAMERA_BATCHES)"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv >> "$S" 2>&1
REACH=$OUT/reach
MADE=0
if [ ! -d "$REACH" ]; then
  MADE=1
  timeout 120 $PY -m lerobot_pdp.cli make-dataset --env reach-around --out "$REACH" --scene 0 --episodes-per-mode 10 \
    --seed 0 --no-progress > "$OUT/logs/dataset.log" 2>&1 || { log "dataset failed"; tail -5 "$OUT/logs/dataset.log" >> "$S"; exit 1; }
fi

if runs select; then
  t=$(cap 200); log "select_action, compiled too (cap ${t}s)"
  timeout -k 5 "$t" $PY benchmarks/bench_select_action.py --device cuda --compile --profile --default-dp-calls 0 \
    --calls 100 --dataset "$REACH" > "$OUT/select_cuda.jsonl" 2> "$OUT/logs/select.err"
  log "select rc=$?"; tail -1 "$OUT/select_cuda.jsonl" >> "$S"
fi
if runs train; then
  for bs in $TRAIN_BATCHES; do
    t=$(cap 200); log "lerobot-train pdp, dp on cuda, B=$bs (cap ${t}s)"
    timeout -k 5 "$t" $PY benchmarks/bench_train_device.py --devices cuda --policies pdp dp --batch-sizes "$bs" \
      --steps 250 --log-freq 25 --num-workers 8 --dataset "$REACH" --logs "$OUT/logs/train_b$bs" \
      > "$OUT/train_cuda_b$bs.jsonl" 2> "$OUT/logs/train_b$bs.err"
    log "train B=$bs rc=$?"; tail -1 "$OUT/train_cuda_b$bs.jsonl" >> "$S"
  done
fi
if runs tests; then
  t=$(cap 300); log "CUDA tests (cap ${t}s)"
  timeout -k 10 "$t" $PY -m pytest -v -p no:cacheprovider -rA --durations=0 -n 8 tests/test_cuda.py \
    tests/test_soft_dtw.py::test_cuda_matches_cpu > "$OUT/cuda_tests.log" 2>&1
  log "tests rc=$?"; grep -E "^(PASSED|FAILED|ERROR)|passed|failed" "$OUT/cuda_tests.log" | tail -25 >> "$S"
fi
if runs cameras; then
  for bs in $CAMERA_BATCHES; do
    t=$(cap 120); log "training steps, 0-2 cameras, B=$bs (cap ${t}s)"
    cams="0 1 2"; [ "$bs" = 256 ] && cams="0"
    timeout -k 5 "$t" $PY benchmarks/bench_cameras.py --device cuda --threads 4 --cameras $cams --calls 20 \
      --eager-pdp --batch "$bs" --fit-calls 2 > "$OUT/cameras_cuda_b$bs.jsonl" 2> "$OUT/logs/cameras_b$bs.err"
    log "cameras B=$bs rc=$?"; grep ratio "$OUT/cameras_cuda_b$bs.jsonl" >> "$S"
  done
fi
if runs cpu; then
  t=$(cap 120); log "lerobot-train pdp on the CPU, B=64 (cap ${t}s)"
  timeout -k 5 "$t" $PY benchmarks/bench_train_device.py --devices cpu --policies pdp --batch-sizes 64 --steps 150 \
    --log-freq 25 --num-workers 8 --dataset "$REACH" > "$OUT/train_cpu_b64.jsonl" 2> "$OUT/logs/train_cpu.err"
  log "cpu rc=$?"; head -1 "$OUT/train_cpu_b64.jsonl" >> "$S"
fi
[ "$MADE" = 1 ] && rm -rf "$REACH"  # a dataset that was there before stays
log done
