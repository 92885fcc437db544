#!/usr/bin/env bash
# Long-time homogeneous cooling (issue 18 part 2) on the GPU machine, in one device call (< 7 min on an H200):
#   - the paper-001 scene (N = 4096, phi = 0.008, L = 2 m; shear-stable) to tau = 100 at e = 0.8 and 0.6,
#     12 seeds each, v_rms = 10 m/s;
#   - the shear-unstable box (N = 32768, phi = 0.1, L = 4 m; L/L_c = 2.6, 3.4) to tau = 100, 4 seeds each;
#   all 32 runs as one CUDA ensemble (5.9e11 particle-steps, ~200-300 s), then the analysis on the device
#   (result files, ~3.8 GB, stay in /tmp there); only the report comes back, packed as $OUT/hcs-long.tgz:
#   hcs-long/{README.md, deviation.png, modes.png, summary.json, series.npz, dsmc.md, dsmc.json, dsmc.png}
#   and hcs-long.log. The stable boxes' deviation is then split into its parts (engine/validation/hcs_dsmc.py:
#   a DSMC and DEM binary collisions, ~2-5 min on the host cores, after the report is written).
# Run from the repository root with .whl carried (../shared/tools/device-wheels.sh):
#   bash bench/device_hcs_long.sh
# Extra arguments go to `python -m engine.validation.hcs_long run`. Split into two calls if one overruns
# (each its own report folder, HCS_LONG_NAME):
#   HCS_LONG_NAME=hcs-long-paper001 bash bench/device_hcs_long.sh --scenes paper001   (4.8e11 particle-steps)
#   HCS_LONG_NAME=hcs-long-unstable bash bench/device_hcs_long.sh --scenes unstable   (1.1e11)
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version --format=csv,noheader
name=${HCS_LONG_NAME:-hcs-long}
mkdir -p "$OUT/$name"
# 395 s (HCS_TIMEOUT overrides): a finished run's report is written well inside the 7-minute call; an overrun still returns the log
timeout ${HCS_TIMEOUT:-395} python3 -m engine.validation.hcs_long run --backend cuda --out-dir "$OUT/$name" \
    --scratch "/tmp/$name" "$@" > "$OUT/$name.log" 2>&1
echo "hcs-long exit $?" >> "$OUT/$name.log"
tail -n 20 "$OUT/$name.log"
rm -rf "/tmp/$name"
# the device tool returns few files per call: one archive of the report and the log
tar czf "$OUT/$name.tgz" -C "$OUT" "$name" "$name.log" && rm -rf "$OUT/$name" "$OUT/$name.log"
