#!/usr/bin/env bash
# One device-tool call (GPU machine, repository root, .whl carried): the paper-001 cooling validation on
# the CUDA backend as one ensemble of 8 runs, then the ensemble benchmark (issue 8).
# Reports land in $OUT/hcs-spheres-paper001-cuda and $OUT/gpu_ensemble.json.
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
t0=$(date +%s)
python3 -c "import sys; from engine.validation import hcs_spheres as h; sys.exit(h.main('$OUT/hcs-spheres-paper001-cuda', seeds=4, quick=False, backend='cuda', ensemble=True))" 2>&1 | grep -v Warning | tail -12
echo "validation wall $(( $(date +%s) - t0 )) s"
cat "$OUT/hcs-spheres-paper001-cuda/REPORT.md" | head -12
rm -f "$OUT"/hcs-spheres-paper001-cuda/*.h5
python3 bench/gpu_ensemble.py --k 1 16 64 256 1024 --out "$OUT/gpu_ensemble.json" 2>&1 | grep -v -i warn | tail -24
