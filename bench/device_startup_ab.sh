#!/usr/bin/env bash
# Issue 14, the GPU start-up thread (engine/startup.py): on the GPU machine, from the repository root,
#   OUT=/tmp/ab bash bench/device_startup_ab.sh [CASES...]        (default case: spheres-2M-f64)
# 1. the GPU tests of the thread and of the cached launches (they also fill the kernel disk cache);
# 2. bench.e2e in fresh processes, DEMQ_GPU_STARTUP=0 and =1 alternated, ROUNDS rounds (default 2) of
#    --reps REPS (default 2) per side, each after an untimed priming run;
# 3. the same case as a second job in one process (--same-process: no start-up), for the ratio beside;
# 4. the start-up stage by stage in fresh processes (bench/e2e_profile.py probes).
# TESTS=0 skips 1., PROBE=0 skips 3. and 4.
set -u
OUT=${OUT:-/tmp/startup-ab}
ROUNDS=${ROUNDS:-2}
REPS=${REPS:-2}
CASES=${*:-spheres-2M-f64}
mkdir -p "$OUT"
# byte-compile what the device tool's wheel install (--no-compile) and this checkout left as source, as a
# user's pip install does: otherwise every fresh process compiles them again when PYTHONDONTWRITEBYTECODE is set
python3 -m compileall -q -j 0 ${PYTHONPATH//:/ } > /dev/null 2>&1
python3 -c "import sys, os; print('dont_write_bytecode', sys.flags.dont_write_bytecode, os.environ.get('PYTHONDONTWRITEBYTECODE'))" | tee "$OUT/env.txt"
nvidia-smi --query-gpu=name,driver_version,persistence_mode --format=csv | tee -a "$OUT/env.txt"
if [ "${TESTS:-1}" = 1 ]; then
    python3 -m pytest -q -s tests/gpu/test_startup_gpu.py "tests/gpu/test_cuda_gpu.py" -k "startup or cached_launches" \
        > "$OUT/gpu-tests.log" 2>&1
    echo "gpu tests exit $?"; tail -3 "$OUT/gpu-tests.log"
fi
for r in $(seq 1 "$ROUNDS"); do
    for on in 0 1; do
        DEMQ_GPU_STARTUP=$on python3 -m bench.e2e --prime --reps "$REPS" --cases $CASES --out "$OUT/r$r-startup$on" \
            > "$OUT/r$r-startup$on.log" 2>&1
        echo "round $r startup=$on: $(grep -E ': wall' "$OUT/r$r-startup$on.log" | tr '\n' ' ')"
        rm -f "$OUT/r$r-startup$on/e2e.md"
    done
done
[ "${PROBE:-1}" = 1 ] || exit 0
# the same job as the second one of a process (warm: no start-up at all), for the ratio beside
python3 -m bench.e2e --same-process --prime --reps "$REPS" --cases $CASES --out "$OUT/same-process" \
    > "$OUT/same-process.log" 2>&1
echo "same process: $(grep -E ': wall' "$OUT/same-process.log" | tr '\n' ' ')"
OUT=$OUT MODES="probe probe probe" python3 bench/e2e_profile.py > "$OUT/probe.log" 2>&1
cat "$OUT/probe.log"
