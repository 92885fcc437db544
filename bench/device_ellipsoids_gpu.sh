#!/usr/bin/env bash
# One device-tool call on the GPU machine (repository root, .whl carried), issue 4 on CUDA, < 9 min in all:
#   1. tests/gpu/test_cuda_ellipsoid_gpu.py (must-show 4: CPU vs GPU float64 <= 1e-9 L after 200 steps ...)
#      -> $OUT/test_cuda_ellipsoid_gpu.log
#   2. the cooling matrix (N = 4096, phi = 0.058, xi x e_n) as ONE ensemble on the GPU, cells chosen to fit
#      the time left (bench/hcs_ellipsoids_cuda.py times a probe ensemble first; dropped cells are listed in
#      plan.json) -> $OUT/hcs-ellipsoids-cuda (H5MD files, REPORT.md without the e_eff DSMC, plan.json)
#   3. bench/gpu_ellipsoid_scaling.py (must-show 5 and issue 8's ensemble rows), rows in priority order
#      until the time is used -> $OUT/gpu_ellipsoid_scaling.json/.md
# Usage: bench/device_ellipsoids_gpu.sh [CELLS...]   CELLS as xi:e (default: all 15 cells)
# Env: TOTAL_S (default 530 s for everything), BENCH_S (seconds kept for step 3, default 190),
#      STEPS (default "test matrix bench"; e.g. STEPS=bench gives the whole call to the scaling bench).
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl && export PYTHONPATH=/tmp/site:$PWD
set -uo pipefail
export PYTHONUNBUFFERED=1
T0=$(date +%s)
TOTAL_S=${TOTAL_S:-530}
BENCH_S=${BENCH_S:-190}
STEPS=${STEPS:-"test matrix bench"}
case " $STEPS " in *" bench "*) ;; *) BENCH_S=0 ;; esac
elapsed() { echo $(( $(date +%s) - T0 )); }
CELLS=("$@")
if [ ${#CELLS[@]} -eq 0 ]; then
  CELLS=(1.15:0.9 1.15:0.95 1.15:0.98 1.5:0.9 1.5:0.95 1.5:0.98 2.0:0.9 2.0:0.95 2.0:0.98 2.5:0.9 2.5:0.95 2.5:0.98 3.0:0.9 3.0:0.95 3.0:0.98)
fi
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
nproc

if [[ " $STEPS " == *" test "* ]]; then
echo "== 1. GPU test (must-show 4) =="
timeout 200 python3 -m pytest tests/gpu/test_cuda_ellipsoid_gpu.py -q -s -p no:cacheprovider > "$OUT/test_cuda_ellipsoid_gpu.log" 2>&1
echo "pytest rc $? at $(elapsed) s"
grep -v -i warn "$OUT/test_cuda_ellipsoid_gpu.log" | grep -E "max rel diff|scene|float32|passed|failed|error|Error|assert" | tail -30
fi

if [[ " $STEPS " == *" matrix "* ]]; then
echo "== 2. cooling matrix as one ensemble =="
VALID_S=$(( TOTAL_S - $(elapsed) - BENCH_S ))
echo "budget for the matrix: $VALID_S s; cells: ${CELLS[*]}"
if [ "$VALID_S" -gt 60 ]; then
  timeout $(( VALID_S + 25 )) python3 bench/hcs_ellipsoids_cuda.py --out "$OUT/hcs-ellipsoids-cuda" --budget-s $(( VALID_S - 10 )) \
      --cells "${CELLS[@]}" 2>&1 | grep -v -i warn | tail -40
  echo "matrix rc ${PIPESTATUS[0]} at $(elapsed) s"
  head -30 "$OUT/hcs-ellipsoids-cuda/REPORT.md" 2>/dev/null
else
  echo "no time left for the matrix"
fi
fi

if [[ " $STEPS " == *" bench "* ]]; then
echo "== 3. scaling bench (must-show 5) =="
LEFT=$(( TOTAL_S - $(elapsed) ))
# a row is not started after LEFT - 70 s (the 16.7 M rows take up to ~60 s each: placement, upload, build)
timeout "$LEFT" python3 bench/gpu_ellipsoid_scaling.py --out "$OUT/gpu_ellipsoid_scaling.json" --budget-s $(( LEFT - 70 )) \
    2>&1 | grep -v -i warn | tail -40
echo "bench rc ${PIPESTATUS[0]}; total $(elapsed) s"
fi
