#!/usr/bin/env bash
# The CUDA checks on a machine with an NVIDIA GPU, as one run (docs/benchmarks.md, "On a GPU"):
#   1. `gpmppi bench planner --backend cuda` at S = 1024 ... 65536 (N = 40), weights fixed and moving every plan,
#      with the device's split (uploads, table collapse, kernel, copies back); S = 2048, N = 100 for the anchor;
#   2. the CUDA tests on the GPU (GPMPPI_CUDA_DEVICE=1: the simulator left off; tests/cuda_mode.py);
#   3. the same sizes on the machine's CPUs (`--backend cpu`), for the ratio.
# Usage: deploy/gpu-check.sh OUT_DIR, from the repository root, with the project importable by `python3`
# (installed, or on PYTHONPATH). Each part has its own time limit and log; a failed part does not stop the next.
set -u
out=${1:?usage: deploy/gpu-check.sh OUT_DIR}
mkdir -p "$out"
py=${PYTHON:-python3}
export PYTHONWARNINGS=ignore::RuntimeWarning PYTHONUNBUFFERED=1
{
  date -u
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv
  nproc
  $py -c 'import sys, numba, numpy; from numba import cuda; print(sys.version); print("numba", numba.__version__,
"numpy", numpy.__version__); print(cuda.get_current_device().name, cuda.get_current_device().compute_capability)'
  $py -m pip show numba-cuda 2>/dev/null | head -2
} > "$out/machine.txt" 2>&1
cat "$out/machine.txt"

bench() {  # bench BACKEND ITERS ARGS...: one JSON line per size into OUT/bench_BACKEND.jsonl
  local backend=$1 iters=$2
  shift 2
  for s in 1024 4096 16384 65536; do
    timeout 150 $py -m tools.cli bench planner --backend "$backend" --samples "$s" --horizon 40 --iters "$iters" \
      --online-weights --json "$@" >> "$out/bench_$backend.jsonl" 2>> "$out/bench.err"
    echo "bench $backend S=$s rc=$? $(date -u +%T)"
  done
}

echo "== 1. CUDA benchmark $(date -u +%T)"
bench cuda 200
timeout 120 $py -m tools.cli bench planner --backend cuda --samples 4096 --horizon 40 --iters 200 --online-weights \
  --table-collapse whole --json >> "$out/bench_cuda_whole.jsonl" 2>> "$out/bench.err"
timeout 120 $py -m tools.cli bench planner --backend cuda --samples 2048 --horizon 100 --iters 200 --json \
  >> "$out/bench_cuda_anchor.jsonl" 2>> "$out/bench.err"
# the costmap critic: circles against a 200 x 200 grid, and a new grid's upload to the device (issue 43)
timeout 90 $py -m tools.cli bench planner --backend cuda --costmap --iters 50 --json \
  >> "$out/bench_cuda_costmap.jsonl" 2>> "$out/bench.err"
tail -n 5 "$out/bench.err"

echo "== 2. CUDA tests on the device $(date -u +%T)"
GPMPPI_CUDA_DEVICE=1 timeout 360 $py -m pytest -p no:cacheprovider -o addopts="" -ra -n 6 --timeout 340 \
  tests/test_planner_cuda.py tests/test_gp_cuda.py tests/test_cuda_compiles.py tests/test_critic_plugins.py \
  tests/test_planner.py::test_backend_choice 2>&1 | tee "$out/tests.log" | tail -n 30

if [ -z "${SKIP_CPU:-}" ]; then  # SKIP_CPU=1: not the CPU part (a rerun that has it already)
  echo "== 3. CPU benchmark $(date -u +%T)"
  bench cpu 50
  tail -n 5 "$out/bench.err"
fi
echo "== done $(date -u +%T)"
