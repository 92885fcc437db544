#!/bin/bash
# Issue 15, GPU lazy sphere orientations: Cundall number and kick_drift share before (8df9308, unpacked in
# .scratch/before: git archive 8df9308 engine tests pyproject.toml bench/*.py | tar -x -C .scratch/before) and
# after (this tree), alternating, one fresh process per row (bench/gpu_scaling.py: loop Cundall of advance() and
# the phase shares from CUDA events; a diagnostic beside the end-to-end figures of bench/e2e.py).
# Usage on the device: bash bench/reports/lazy-orientation-gpu/ab.sh OUTDIR [N ...]
out=${1:?outdir}; shift
ns=${*:-2097152 16777216}
nvidia-smi --query-gpu=name,clocks.max.sm,memory.total --format=csv | tee -a "$out/ab.log"
for prec in float64 float32; do
  for n in $ns; do
    for side in after before; do
      d=.; [ "$side" = before ] && d=.scratch/before
      echo "== $side $prec $n" | tee -a "$out/ab.log"
      (cd "$d" && PYTHONPATH=/tmp/site:$PWD timeout 240 python3 bench/gpu_scaling.py --n "$n" --phi 0.058 \
        --precision "$prec" --reps 5 2>&1 | grep -v '^$' | sed "s/^/$side /") | tee -a "$out/ab.log"
    done
  done
done
