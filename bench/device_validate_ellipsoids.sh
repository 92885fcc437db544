#!/usr/bin/env bash
# Ellipsoid homogeneous-cooling validation (issue 4, must-show 3) on the device machine's 16 CPU cores, one call:
# the paper-003 scene (N = 4096, phi = 0.058, Gamma_0 t_end = 40) for the cells given as "xi:e ..." in
# $CELLS (default: all 15 of xi in {1.15,1.5,2,2.5,3} x e_n in {0.9,0.95,0.98}), seed $SEED, one run per core
# with 1 Numba thread each (the ellipsoid loop scales badly on 2 threads of a shared host). The simulation
# step is bounded by $LIMIT seconds so that finished runs always come back: the H5MD files are tarred into
# $OUT/h5.tar.gz and analysed here with
#   python -c "from engine.validation import hcs_ellipsoids as h; h.main(DIR, simulate=False)"
# (which also runs the e_eff(D) DSMC). A device-side report without DSMC lands in $OUT/dev.
# Run from the repository root with .whl carried.
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 NUMBA_NUM_THREADS=1
CELLS=${CELLS:-"1.15:0.9 1.15:0.95 1.15:0.98 1.5:0.9 1.5:0.95 1.5:0.98 2.0:0.9 2.0:0.95 2.0:0.98 2.5:0.9 2.5:0.95 2.5:0.98 3.0:0.9 3.0:0.95 3.0:0.98"}
SEED=${SEED:-0}; LIMIT=${LIMIT:-530}
lscpu | grep -E "Model name|^CPU\(s\)|Thread"
python3 -c "from engine.simulate import run; from engine.spec import SimulationSpec as S; run(S(shape='ellipsoid', elongation=2.0, e_t=-1.0, n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=1e-3, thermalization=0.2, backend='cpu', snapshots=0), '/tmp/warm.h5')"
mkdir -p /tmp/runs "$OUT/dev"
run_cell() { python3 -c "import sys; from engine.validation import hcs_ellipsoids as h; from pathlib import Path; print(h._one((float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), 'cpu', False, Path('/tmp/runs')/f'xi{float(sys.argv[1])}_e{float(sys.argv[2])}_seed{sys.argv[3]}.h5', 1)))" "$@"; }
t0=$(date +%s)
for c in $CELLS; do (timeout "$LIMIT" bash -c "$(declare -f run_cell); run_cell ${c%%:*} ${c##*:} $SEED" || echo "cell $c seed $SEED: stopped (rc $?)") & done
wait
echo "simulations: $(( $(date +%s) - t0 )) s"
tar czf "$OUT/h5.tar.gz" -C /tmp/runs $(cd /tmp/runs && ls *.h5 *.part 2>/dev/null)
ls -la /tmp/runs
