#!/usr/bin/env bash
# GPU rows of the issue-6 accuracy report, in one device call (CUDA backend for every sphere row; the ellipsoid
# rows are in the CPU report, hence --no-ellipsoids):
#   python -m bench.accuracy --backend cuda   -> $OUT/accuracy-cuda/{REPORT.md,accuracy.png,summary.json}
# plus $OUT/accuracy-cuda.log. The REPORT.md names the GPU (the backend's device name). Expected: about 4 min on
# one H200 (the previous full report took 3.9 min; this one drops the fine dt scan and the rough skin rows and
# adds binary-collision samples and a skin sweep at N = 262144); the timeout keeps it under the 10-min limit.
# The specialisation report (bench/reports/specialisation-cuda) is not re-run: its scenes pin L_v = 0.4 a and
# nothing it measures changed; to re-run it: python3 -m bench.specialisation --backend cuda --n 262144
# --no-ellipsoids -o "$OUT/specialisation-cuda" (2.2 min).
# Run from the repository root with .whl carried (../shared/tools/device-wheels.sh; DESIGN §8: numba-cuda
# 0.30.4 needs numpy < 2.4).
# Sizes: the GPU is launch-bound below ~1e5 particles (bench/RESULTS.md), so the accuracy gases use N = 16384
# (the CPU report 2048) and the skin sweep N = 262144 (CPU 4096).
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
start=$SECONDS
timeout 540 python3 -m bench.accuracy --backend cuda --n 16384 --sweep-n 262144 --no-ellipsoids \
    -o "$OUT/accuracy-cuda" > "$OUT/accuracy-cuda.log" 2>&1
echo "accuracy exit $? after $((SECONDS - start)) s"
sed -n '/^## Verdict/,/^## Binary/p' "$OUT/accuracy-cuda/REPORT.md" 2>/dev/null || tail -n 30 "$OUT/accuracy-cuda.log"
sed -n '/^## Verlet skin/,/^Raw rows/p' "$OUT/accuracy-cuda/REPORT.md" 2>/dev/null
