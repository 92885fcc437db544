"""`python -m bench`: the runner lists every benchmark, runs one by name with its own arguments, and writes its
outputs under --out DIR (default ./bench-out/<name>/ in the working directory), never into the bench package."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import bench
import bench as cli

ROOT = Path(__file__).resolve().parents[2]


def _bench(args, cwd):
    """`python -m bench ARGS` from a folder outside the checkout (the checkout on PYTHONPATH); the ceiling only
    catches a hang."""
    return subprocess.run([sys.executable, "-m", "bench", *args], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": "1"}, timeout=900)


def _package_files():
    """The bench folder's entries, less Python's bytecode cache."""
    return sorted(p.name for p in Path(bench.__file__).parent.iterdir() if p.name != "__pycache__")


def test_every_benchmark_is_registered():
    modules = {p.stem for p in Path(bench.__file__).parent.glob("*.py")} - {"__init__", "__main__"}
    assert set(cli.BENCHMARKS) == modules
    listing = cli.usage()
    assert all(name in listing for name in modules)


def test_out_is_split_from_the_benchmark_arguments():
    assert cli._split_out(["--n", "3", "--out", "d", "--x"]) == ("d", ["--n", "3", "--x"])
    assert cli._split_out(["--out=d2", "a"]) == ("d2", ["a"])
    assert cli._split_out(["--n", "3"]) == (None, ["--n", "3"])


def test_default_out_is_under_the_working_directory(tmp_path):
    """A benchmark that takes --out, run without one: its JSON lands in ./bench-out/<name>/, with the log."""
    before = _package_files()
    p = _bench(["multigrid_cost", "--n", "2000", "--ratios", "1", "--reps", "1", "--threads", "1"], tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    out = tmp_path / "bench-out" / "multigrid_cost"
    assert json.loads((out / "multigrid_cost.json").read_text())["rows"][0]["n_levels"] == 1
    assert "| 1 |" in (out / "stdout.log").read_text()
    assert _package_files() == before


def test_named_out_and_unknown_name(tmp_path):
    p = _bench(["multigrid-cost", "--n", "2000", "--ratios", "1", "--reps", "1", "--threads", "1",
                "--out", str(tmp_path / "mine")], tmp_path)
    assert p.returncode == 0, p.stderr[-3000:]
    assert (tmp_path / "mine" / "multigrid_cost.json").is_file() and not (tmp_path / "bench-out").exists()
    p = _bench(["no_such_bench"], tmp_path)
    assert p.returncode == 2 and "no benchmark named 'no_such_bench'" in p.stderr
