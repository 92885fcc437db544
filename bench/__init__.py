"""Benchmarks and stress tests of demq, run from a checkout: ``python -m bench <name> [--out DIR] ...``.

Not installed with the package (pyproject installs engine, jobs and service only). Every benchmark writes its
outputs under the folder named by ``--out`` (default ``./bench-out/<name>/`` under the current working
directory), never into this folder.

``python -m bench`` lists them; ``python -m bench <name> --help`` shows a benchmark's own options. The benchmark
runs as ``python -m bench.<name>`` would, with its own arguments. Its outputs go under ``--out DIR`` (default
./bench-out/<name>/ under the current working directory); a copy of everything it prints goes to
DIR/stdout.log, which for the diagnostics that only print is their whole output.
"""

from __future__ import annotations

import ast
import runpy
import sys
from contextlib import contextmanager
from pathlib import Path


def out_dir(path: str | Path | None, name: str) -> Path:
    """The folder a benchmark writes into, created: ``path`` when given, else ./bench-out/<name>/ under the
    current working directory."""
    out = Path(path) if path else Path.cwd() / "bench-out" / name
    out.mkdir(parents=True, exist_ok=True)
    return out


#: Every benchmark, by module name, and whether it takes ``--out DIR`` itself (it writes reports or JSON there);
#: the others only print, and their output is the DIR/stdout.log the runner keeps.
BENCHMARKS: dict[str, bool] = {
    # speed (Cundall numbers) and time to result
    "gpu_scaling": True, "gpu_ensemble": True, "vs_lammps": True, "e2e": True, "multigrid_cost": True,
    "specialisation": True, "vs_jaxmd": True, "large_scenes": True,
    "loop_ab": False, "step_bytes": True, "host_memory": False, "download_speed": False, "cpu_default_job": False,
    # accuracy against cost, stability, bit identity
    "accuracy": True, "stability": True, "bit_identity": False,
    # the service under load
    "load_service": False, "small_jobs": True, "first_job": True, "gpu_workers": True,
}


def _summary(name: str) -> str:
    """The first line of a benchmark's docstring, read without importing it (imports compile kernels)."""
    doc = ast.get_docstring(ast.parse((Path(__file__).parent / f"{name}.py").read_text())) or ""
    return doc.splitlines()[0] if doc else ""


def usage() -> str:
    lines = ["usage: python -m bench <name> [--out DIR] [args]   (python -m bench <name> --help for its options)",
             "", "Benchmarks (outputs under --out DIR, default ./bench-out/<name>/):"]
    lines += [f"  {name:32s} {_summary(name)}" for name in sorted(BENCHMARKS)]
    return "\n".join(lines)


def _split_out(args: list[str]) -> tuple[str | None, list[str]]:
    """(the value of --out, the arguments without it)."""
    rest, value, i = [], None, 0
    while i < len(args):
        if args[i] == "--out":
            if i + 1 >= len(args):
                raise SystemExit("python -m bench: --out needs a folder")
            value, i = args[i + 1], i + 2
            continue
        if args[i].startswith("--out="):
            value = args[i].split("=", 1)[1]
        else:
            rest.append(args[i])
        i += 1
    return value, rest


class _Tee:
    """A text stream writing to two others (the terminal and the log file)."""

    def __init__(self, *streams):
        self.streams = streams

    def write(self, text: str) -> int:
        for s in self.streams:
            s.write(text)
        return len(text)

    def flush(self) -> None:
        for s in self.streams:
            s.flush()

    def isatty(self) -> bool:
        return False


@contextmanager
def _tee_stdout(path: Path):
    with open(path, "a") as log:
        saved = sys.stdout
        sys.stdout = _Tee(saved, log)
        try:
            yield
        finally:
            sys.stdout.flush()
            sys.stdout = saved


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help", "list"):
        print(usage())
        return 0
    name = argv[0].replace("-", "_")
    if name not in BENCHMARKS:
        print(f"python -m bench: no benchmark named {argv[0]!r}\n\n{usage()}", file=sys.stderr)
        return 2
    given, rest = _split_out(argv[1:])
    wants_help = "-h" in rest or "--help" in rest
    out = None if wants_help else out_dir(given, name)
    module_argv = (["--out", str(out)] if BENCHMARKS[name] and out is not None else []) + rest
    saved_argv = sys.argv
    sys.argv = [f"python -m bench {name}", *module_argv]
    try:
        if out is None:
            runpy.run_module(f"bench.{name}", run_name="__main__", alter_sys=True)
        else:
            with _tee_stdout(out / "stdout.log"):
                runpy.run_module(f"bench.{name}", run_name="__main__", alter_sys=True)
    except SystemExit as stop:
        if isinstance(stop.code, str):
            print(stop.code, file=sys.stderr)
        return stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
    finally:
        sys.argv = saved_argv
    return 0
