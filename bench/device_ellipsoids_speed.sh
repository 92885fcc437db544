#!/usr/bin/env bash
# One device call (NVIDIA H200, repository root, PYTHONPATH set by the caller), issue 4 must-show 5 after the
# exact screens before the Perram-Wertheim solve, < 4 min:
#   1. tests/gpu/test_cuda_ellipsoid_gpu.py (CPU <-> GPU agreement, float32, instability, ensembles)
#      -> $OUT/test_cuda_ellipsoid_gpu.log
#   2. bench/gpu_ellipsoid_scaling.py: Cundall number of xi = 2, phi = 0.058 ellipsoids at N = 2 097 152 and
#      16 777 216 in float64 and float32 (median of 3); float64 2^21 control rows in the same process with the
#      screens off (the code path before them) and with PW tolerance 1e-10; then the sphere rows at the same N
#      for the ratio, as long as the time lasts -> $OUT/gpu_ellipsoid_speed.json/.md
set -uo pipefail
export PYTHONUNBUFFERED=1
: "${OUT:?set OUT to the folder that comes back}"
T0=$(date +%s)
elapsed() { echo $(( $(date +%s) - T0 )); }
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader

echo "== 1. GPU test =="
timeout 125 python3 -m pytest -q tests/gpu/test_cuda_ellipsoid_gpu.py -p no:cacheprovider \
    > "$OUT/test_cuda_ellipsoid_gpu.log" 2>&1
echo "pytest rc $? at $(elapsed) s"
tail -3 "$OUT/test_cuda_ellipsoid_gpu.log"

echo "== 2. Cundall number =="
LEFT=$(( 228 - $(elapsed) ))
# no new row after LEFT - 50 s (a 16.7 M ellipsoid row with its placement takes up to ~50 s); the JSON is
# rewritten after every row, so a row cut by the timeout loses only itself
timeout "$LEFT" python3 bench/gpu_ellipsoid_scaling.py --n 2097152 16777216 --precision float64 float32 \
    --no-ensemble --spheres-last --controls --budget-s $(( LEFT - 50 )) --out "$OUT/gpu_ellipsoid_speed.json" \
    2>&1 | grep -v -i warn | tail -22
echo "bench rc ${PIPESTATUS[0]}; total $(elapsed) s"
