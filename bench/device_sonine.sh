#!/usr/bin/env bash
# Sonine coefficient a2 of the homogeneous cooling state (issue 18 part 1) on the GPU machine, in one call:
# `demq validate sonine --ensemble --backend cuda`: smooth spheres e_n = 0.9, 0.8, 0.6, 0.4 and rough spheres
# e_n = 0.8, e_t = 0.8 / 0.4, $SEEDS seeds each (default 64; N = 1000, phi = 0.05, L = 1.26 m: below the
# shear-mode threshold of every case), all 6 x $SEEDS scenes as
# ONE CUDA ensemble, then the DSMC references on the host cores (one thread per case) and the report
# (README.md, summary.json, sonine.png) in $OUT (default bench/reports/sonine). The H5MD files are deleted
# afterwards. Expected (N = 1000 x 64 seeds): ~1.3e11 particle-steps, ~1.5 min of GPU, ~15 s of DSMC.
# Run from the repository root with .whl carried (../shared/tools/device-wheels.sh), or in any environment
# where `import engine` works (then the pip line is skipped).
set -uo pipefail
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1
# optional box-size check: N=4000 L=2.0 (same phi; above the shear-mode threshold at e_n <= 0.6), CASES="0.4:-1 0.6:-1"
# the device tool returns few files per call: the report is also packed into $OUT.tgz
OUT=${OUT:-bench/reports/sonine}; SEEDS=${SEEDS:-64}; BACKEND=${BACKEND:-cuda}; N=${N:-0}; L=${L:-0}; CASES=${CASES:-}
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader 2>/dev/null || true
t0=$(date +%s)
python3 -c "import sys; from engine.validation import sonine as v; c = [tuple(map(float, x.split(':'))) for x in sys.argv[6].split()] or None; sys.exit(v.main(sys.argv[1], seeds=int(sys.argv[2]), backend=sys.argv[3], ensemble=True, n_particles=int(sys.argv[4]), box_length=float(sys.argv[5]), cases=c))" "$OUT" "$SEEDS" "$BACKEND" "$N" "$L" "$CASES" 2>&1 | tee "$OUT.log"
rc=${PIPESTATUS[0]}
echo "sonine validation exit $rc in $(( $(date +%s) - t0 )) s" | tee -a "$OUT.log"
mkdir -p "$OUT" && mv "$OUT.log" "$OUT/run.log"
rm -f "$OUT"/*.h5 "$OUT"/*.xmf
tar czf "$OUT.tgz" -C "$(dirname "$OUT")" "$(basename "$OUT")"
exit $rc
