#!/usr/bin/env bash
# Homogeneous-cooling validation on the GPU machine (device tool), in one call:
#   - the paper-001 scene (N = 4096, phi = 0.008, tau <= 10, 4 seeds x 2 cases) with the CPU backend on the
#     machine's 16 cores, 8 runs at a time with 2 Numba threads each;
#   - the CI-size scene (N = 4000, phi = 0.05, tau <= 3, 4 seeds x 2 cases) with the CUDA backend.
# Reports land in $OUT/cpu-full and $OUT/gpu-quick (REPORT.md, summary.json, hcs_spheres.png).
# Run from the repository root with .whl carried (../shared/tools/device-wheels.sh).
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
nproc
val() { python3 -c "import sys; from engine.validation import hcs_spheres as h; sys.exit(h.main(sys.argv[1], seeds=4, quick=sys.argv[2]=='quick', backend=sys.argv[3], jobs=int(sys.argv[4]), threads=int(sys.argv[5])))" "$@"; }
# warm the CPU kernel cache once so the 8 spawned runs load instead of compiling
python3 -c "from engine.simulate import run; from engine.spec import SimulationSpec as S; run(S(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=1e-3, thermalization=0.2, backend='cpu', snapshots=0), '/tmp/warm.h5')"
(val "$OUT/gpu-quick" quick cuda 1 0 > "$OUT/gpu-quick.log" 2>&1; echo "gpu-quick exit $?" >> "$OUT/gpu-quick.log") &
val "$OUT/cpu-full" full cpu 8 2 > "$OUT/cpu-full.log" 2>&1; echo "cpu-full exit $?"
wait
cat "$OUT/gpu-quick.log"; tail -n 12 "$OUT/cpu-full.log"
rm -f "$OUT"/*/*.h5
