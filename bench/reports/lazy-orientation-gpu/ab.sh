#!/bin/bash
# Issue 15, GPU lazy sphere orientations: Cundall number and kick_drift share before (8df9308, unpacked in
# .scratch/before: git archive 8df9308 engine tests pyproject.toml bench/*.py | tar -x -C .scratch/before) and
# after (this tree), alternating, one fresh process per row (bench/gpu_scaling.py: loop Cundall of advance() and
# the phase shares from CUDA events; a diagnostic beside the end-to-end figures of bench/e2e.py).
# Usage on the device: ROUNDS=3 PRECS="float64 float32" bash bench/reports/lazy-orientation-gpu/ab.sh OUTDIR [N ...]
out=${1:?outdir}; shift
ns=${*:-2097152 16777216}
nvidia-smi --query-gpu=name,clocks.sm,clocks.max.sm,temperature.gpu,memory.total --format=csv | tee -a "$out/ab.log"
for r in $(seq "${ROUNDS:-1}"); do
 for prec in ${PRECS:-float64 float32}; do
  for n in $ns; do
    for side in after before; do
      d=.; [ "$side" = before ] && d=.scratch/before
      echo "== round $r $side $prec $n" | tee -a "$out/ab.log"
      (cd "$d" && PYTHONPATH=/tmp/site:$PWD timeout 240 python3 bench/gpu_scaling.py --n "$n" --phi 0.058 \
        --precision "$prec" --reps 5 --target-s 0.6 2>&1 | grep -v 'Warning\|warn(' | grep -v '^$' \
        | sed "s/^/$side /") | tee -a "$out/ab.log"
    done
  done
 done
done
nvidia-smi --query-gpu=name,clocks.sm,temperature.gpu --format=csv | tee -a "$out/ab.log"
