#!/usr/bin/env bash
# Issue 14, the worker's standby simulation process (jobs/worker.py) and the GPU start-up thread: on the GPU
# machine, from the repository root,
#   OUT=/tmp/ws bash bench/device_worker_standby.sh [CASES...]   (default: worker-2M-f64 worker-256x4096-20k)
# 1. the GPU test of the start-up thread and the worker's standby tests (a GPU is present: standby 'auto' = on);
# 2. per case, bench.e2e in fresh processes (--prime, --reps REPS, default 2) for: DEMQ_WORKER_STANDBY=off,
#    =on with the submit right after the server is up, =on after IDLE seconds of idle worker (default 5).
set -u
OUT=${OUT:-/tmp/worker-standby}
REPS=${REPS:-2}
IDLE=${IDLE:-5}
CASES=${*:-worker-2M-f64 worker-256x4096-20k}
mkdir -p "$OUT"
python3 -m compileall -q -j 0 ${PYTHONPATH//:/ } > /dev/null 2>&1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/env.txt"
python3 -m pytest -q -s tests/gpu/test_startup_gpu.py tests/jobs/test_worker.py -k "startup or standby" \
    > "$OUT/tests.log" 2>&1
echo "tests exit $?"; tail -2 "$OUT/tests.log"
for case in $CASES; do
    for cfg in off:0 on:0 on:$IDLE; do
        sb=${cfg%%:*}; idle=${cfg##*:}
        DEMQ_WORKER_STANDBY=$sb DEMQ_E2E_WORKER_IDLE_S=$idle python3 -m bench.e2e --prime --reps "$REPS" \
            --cases "$case" --out "$OUT/$case-$sb-idle$idle" > "$OUT/$case-$sb-idle$idle.log" 2>&1
        echo "$case standby=$sb idle=${idle}s: $(grep -E ': wall' "$OUT/$case-$sb-idle$idle.log" | tr '\n' ' ')"
        rm -f "$OUT/$case-$sb-idle$idle/e2e.md"
    done
done
