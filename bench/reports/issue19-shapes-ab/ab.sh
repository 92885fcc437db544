# A/B of the issue-19 shape-package refactor: 906f745 (.scratch/ref) against the working tree, alternating sides,
# each side's bench.e2e in fresh processes (--prime fills the kernel cache; median of --reps).
set -u
SIDES=${SIDES:-"new old new old"}; REPS=${REPS:-2}; CASES=${CASES:-"spheres-2M-f64 ellipsoids-2M"}
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
i=0
for side in $SIDES; do
  i=$((i+1))
  if [ "$side" = old ]; then dir=$PWD/.scratch/ref; else dir=$PWD; fi
  echo "=== $i $side ($dir)"
  (cd "$dir" && PYTHONPATH=/tmp/site:$dir timeout 280 python3 -m bench.e2e --prime --reps "$REPS" --cases $CASES --out "$OUT/$i-$side") 2>&1 | tail -8
done
