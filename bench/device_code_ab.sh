#!/usr/bin/env bash
# A/B of two checkouts on the GPU machine, fresh processes, alternated on one machine (issue 14: time to result):
#   OUT=/tmp/ab BASE=.scratch/base bash bench/device_code_ab.sh [CASES...]      (default: spheres-2M-f64)
# BASE is a copy of the code before the change (e.g. `git archive HEAD | tar -x -C .scratch/base`); this
# checkout is the code after it. ROUNDS rounds (default 2) of bench.e2e --prime --reps REPS (default 2) per side,
# base first; SIDE_ENV="VAR=value ..." adds a third side, this checkout under those settings (e.g.
# SIDE_ENV=DEMQ_OVERLAP_RECORDS=0). First the GPU tests of the start-up, the kernel cache loads and the overlapped
# records (TESTS=0 skips); last the start-up stage by stage and a cProfile of a 200-step job on this checkout
# (bench/e2e_profile.py, PROBE=0 skips).
set -u
OUT=${OUT:-/tmp/code-ab}
BASE=${BASE:-.scratch/base}
ROUNDS=${ROUNDS:-2}
REPS=${REPS:-2}
CASES=${*:-spheres-2M-f64}
HERE=$PWD
mkdir -p "$OUT"
# byte-compile what the wheel install (--no-compile) and the checkouts left as source, as a user's pip install does
python3 -m compileall -q -j 0 ${PYTHONPATH//:/ } "$BASE" > /dev/null 2>&1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader | tee "$OUT/env.txt"
echo "base: $(cat "$BASE/.base-commit" 2>/dev/null)  new: $(git -C "$HERE" rev-parse --short HEAD 2>/dev/null) + working tree" \
    | tee -a "$OUT/env.txt"
if [ "${TESTS:-1}" = 1 ]; then
    python3 -m pytest -q -s tests/gpu/test_startup_gpu.py tests/gpu/test_overlapped_records_gpu.py \
        tests/gpu/test_cuda_gpu.py -k "startup or cached_launches or overlapped" \
        > "$OUT/gpu-tests.log" 2>&1
    echo "gpu tests exit $?"; tail -3 "$OUT/gpu-tests.log"
fi
SIDES="base new"; [ -n "${SIDE_ENV:-}" ] && SIDES="$SIDES new-env"
for r in $(seq 1 "$ROUNDS"); do
    for side in $SIDES; do
        dir=$HERE; [ "$side" = base ] && dir=$BASE
        envs=""; [ "$side" = new-env ] && envs=$SIDE_ENV
        (cd "$dir" && env $envs PYTHONPATH="${PYTHONPATH%%:*}:$dir" python3 -m bench.e2e --prime --reps "$REPS" \
            --cases $CASES --out "$OUT/r$r-$side") > "$OUT/r$r-$side.log" 2>&1
        echo "round $r $side: $(grep -E ': wall' "$OUT/r$r-$side.log" | tr '\n' ' ')"
        mv "$OUT/r$r-$side/e2e.json" "$OUT/r$r-$side.json" 2>/dev/null; rm -rf "$OUT/r$r-$side"
    done
done
if [ "${PROBE:-1}" = 1 ]; then
    OUT=$OUT MODES="probe probe profile" python3 bench/e2e_profile.py > "$OUT/probe.log" 2>&1
    cut -c1-600 "$OUT/probe.log"
fi
