#!/usr/bin/env bash
# Rough spheroids (issue 17) on the GPU machine, one device call per mode (run from the repository root with
# .whl carried: ../shared/tools/device-wheels.sh); everything comes back packed as $OUT/rough-<mode>.tgz:
#   bash bench/device_rough_spheroids.sh tests      # tests/gpu (all of it) + bench.e2e: 2M ellipsoids xi = 2,
#                                                   # phi = 0.058, f64, smooth vs rough (prime + 2 reps), < 8 min
#   bash bench/device_rough_spheroids.sh validate   # demq validate hcs-rough-spheroids --backend cuda: the
#                                                   # xi -> 1 limit (8 + 8 seeds) and the 3 x 4 x 8 map, < 8 min
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
: "${OUT:?set OUT to the folder that comes back}"
mode=${1:-tests}
dir="$OUT/rough-$mode"
mkdir -p "$dir"
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$dir/gpu.txt"
T0=$(date +%s)
if [ "$mode" = tests ]; then
    timeout 330 python3 -m pytest -q -s tests/gpu -p no:cacheprovider > "$dir/tests_gpu.log" 2>&1
    echo "tests/gpu rc $? after $(( $(date +%s) - T0 )) s"; tail -3 "$dir/tests_gpu.log"
    timeout $(( 560 - ($(date +%s) - T0) )) python3 -m bench.e2e --prime --reps 2 \
        --cases ellipsoids-2M ellipsoids-rough-2M --out "$dir/e2e" > "$dir/e2e.log" 2>&1
    echo "e2e rc $? after $(( $(date +%s) - T0 )) s"; cat "$dir/e2e/e2e.md" 2>/dev/null | tail -6
else
    timeout 560 python3 -m service.cli validate hcs-rough-spheroids --backend cuda -o /tmp/hcs-rough-spheroids \
        > "$dir/validate.log" 2>&1
    echo "validate rc $? after $(( $(date +%s) - T0 )) s"; grep -v -i warn "$dir/validate.log" | tail -25
    cp /tmp/hcs-rough-spheroids/{REPORT.md,summary.json,rough_spheroids.png} "$dir/" 2>/dev/null
fi
tar czf "$OUT/rough-$mode.tgz" -C "$OUT" "rough-$mode" && rm -rf "$dir"
