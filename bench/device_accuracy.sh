#!/usr/bin/env bash
# GPU rows of the issue-6 reports, in one device call (CUDA backend for every sphere row; the ellipsoid
# rows are CPU-only in this engine and are in the CPU reports already, hence --no-ellipsoids):
#   demq bench specialisation --backend cuda   -> $OUT/specialisation-cuda/{REPORT.md,summary.json}
#   demq bench accuracy --backend cuda         -> $OUT/accuracy-cuda/{REPORT.md,accuracy.png,summary.json}
# Each REPORT.md names the GPU (the backend's device name). Logs: $OUT/*.log.
# Run from the repository root with .whl carried (../shared/tools/device-wheels.sh; DESIGN §8: numba-cuda
# 0.30.4 needs numpy < 2.4).
# Sizes: the GPU is launch-bound below ~1e5 particles (bench/RESULTS.md), so the specialisation scenes use
# N = 262144 and the accuracy gases N = 16384 (the CPU reports use 4096 and 2048).
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
start=$SECONDS
python3 -m bench.specialisation --backend cuda --n 262144 --no-ellipsoids -o "$OUT/specialisation-cuda" \
    > "$OUT/specialisation-cuda.log" 2>&1
echo "specialisation exit $? after $((SECONDS - start)) s"
python3 -m bench.accuracy --backend cuda --n 16384 --no-ellipsoids -o "$OUT/accuracy-cuda" \
    > "$OUT/accuracy-cuda.log" 2>&1
echo "accuracy exit $? after $((SECONDS - start)) s"
grep -v '^|' "$OUT/specialisation-cuda.log" | tail -n 5
sed -n '1,/^## Binary/p' "$OUT/accuracy-cuda/REPORT.md" 2>/dev/null || tail -n 30 "$OUT/accuracy-cuda.log"
