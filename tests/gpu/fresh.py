"""What the GPU tests that compare fresh-process jobs share: a job run in a child process (with environment
variables added), and a result file's datasets."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import h5py

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def run_job(child: str, kw: dict, out, env: dict, tag: str):
    """Run ``python -c child JSON(kw) out`` in a fresh process with ``env`` added (this checkout first on the path) and
    return the JSON the child printed after ``tag`` on its last such line."""
    full = {**os.environ, **env,
            "PYTHONPATH": os.pathsep.join([ROOT] + [x for x in [os.environ.get("PYTHONPATH")] if x])}
    p = subprocess.run([sys.executable, "-c", child, json.dumps(kw), str(out)], env=full, cwd=ROOT,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    line = [x for x in p.stdout.splitlines() if x.startswith(tag + " ")][-1]
    return json.loads(line[len(tag) + 1:])


def datasets(path) -> dict:
    """Every dataset of an HDF5 file, by path."""
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out
