#!/usr/bin/env bash
# One job's threads against PyTorch on the same CPU and on its GPU, in one run (the table of
# docs/performance.md, "Threads of one job"). SafeDICE's main loop and discriminator step at
# batch 512, hidden [256, 256], on Walker-like shapes (obs 17, act 6: every thread count, ours
# and PyTorch's) and on the paper's RWRL Cartpole (obs 5, act 1: ours at every count, PyTorch at
# the most and on the GPU); each baseline's step at 1 thread and the most.
#
#   BIN=target/release/safedice PY=python3 OUT=/tmp/threads bench/threads_scaling.sh
#   THREADS=1,2 bench/threads_scaling.sh          # a 2-core machine (no GPU: that step fails)
#   BASELINES=0 bench/threads_scaling.sh          # SafeDICE and PyTorch only
set -u
BIN=${BIN:-target/release/safedice}
PY=${PY:-python3}
OUT=${OUT:-/tmp/threads-scaling}
THREADS=${THREADS:-1,2,4,8,16}
MOST=${THREADS##*,}
export PYTHONUNBUFFERED=1
mkdir -p "$OUT"
{ lscpu; nvidia-smi -L 2>/dev/null; "$PY" -c 'import torch; print("torch", torch.__version__)'; } \
  >"$OUT/machine.txt" 2>&1

torch_cpu() { # obs act threads...
  local obs=$1 act=$2; shift 2
  for t in "$@"; do
    "$PY" bench/pytorch_reference.py --obs-dim "$obs" --act-dim "$act" --iters 150 --threads "$t"
  done
}

"$BIN" speed --obs-dim 17 --act-dim 6 --threads "$THREADS" --iterations 300 --repeats 3 \
  | tee "$OUT/ours-obs17.txt"
torch_cpu 17 6 ${THREADS//,/ } 2>&1 | tee "$OUT/torch-cpu-obs17.txt"
"$PY" bench/pytorch_reference.py --obs-dim 17 --act-dim 6 --iters 1000 --device cuda 2>&1 \
  | tee "$OUT/torch-gpu-obs17.txt"

"$BIN" speed --obs-dim 5 --act-dim 1 --threads "$THREADS" --iterations 300 --repeats 3 \
  | tee "$OUT/ours-obs5.txt"
torch_cpu 5 1 "$MOST" 2>&1 | tee "$OUT/torch-cpu-obs5.txt"
"$PY" bench/pytorch_reference.py --obs-dim 5 --act-dim 1 --iters 1000 --device cuda 2>&1 \
  | tee "$OUT/torch-gpu-obs5.txt"

[ "${BASELINES:-1}" = 0 ] && exit 0
for algorithm in bc dwbc ppl dexperts; do
  "$BIN" speed --algorithm "$algorithm" --threads "1,$MOST" --iterations 300 --repeats 3
done | tee "$OUT/baselines.txt"
