"""DRAM bytes per particle-step of every kernel of a step, from Nsight Compute, on the gas that collides.

Runs ``ncu`` (Nsight Compute, on the PATH) over bench/loop_ab.py for each case and variant: the force and kick-drift
kernels of the per-phase loop (``forces``, ``kick_drift``, ``forces_kick_drift`` and their record-summing forms
``forces_observe*``), ``--launch-count`` launches after ``--launch-skip`` (past loop_ab's 20-step compile runs),
each with its DRAM bytes read and written, its duration and the DRAM throughput as a percentage of the peak
(``gpu__dram_throughput``), the warps active and the registers. The table gives, per kernel, the median over its
launches of the bytes per particle (read + written over N) and of the percentage of peak, and the step's total
(the kernels of one step: forces + kick_drift, or the fused forces_kick_drift). The clocks are left alone
(``--clock-control none``, as the timed benchmarks run). The profiled process runs without the GPU start-up
threads (loop_ab's ``startup`` switch): the loop's kernels are the same, and no second thread calls the driver
while Nsight Compute's injection starts (before engine/driver/simulate.py waited for the start-up thread's probe,
5 of 6 such runs crashed at their first CUDA call).

    python -m bench step_bytes --cases rough-8M-f32 elastic-8M-f32 --variants default skip_cold
    python -m bench step_bytes --cases rough-8M-f32 --phi 0.2

Cases and variants are bench/loop_ab.py's (the JAX-MD cases, from the random start: an equilibrium gas; and its
extra cases, such as 256 packed scenes of 4096 against one scene of 2^20, bytes over all the scenes' particles).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))

#: the loop's kernels, longest name first (a kernel's name is matched in ncu's function name)
KERNELS = ("forces_observe_kick_drift", "forces_observe", "forces_kick_drift", "forces", "kick_drift")
#: the kernels of one step of each loop kind
STEP = {"two launches": ("forces", "kick_drift"), "fused": ("forces_kick_drift",)}
METRICS = ("gpu__time_duration.sum", "dram__bytes_read.sum", "dram__bytes_write.sum",
           "gpu__dram_throughput.avg.pct_of_peak_sustained_elapsed",
           "sm__warps_active.avg.pct_of_peak_sustained_active", "launch__registers_per_thread")


def kernel_of(function_name: str):
    """The loop kernel a profiled function's (mangled or demangled) name belongs to, or None."""
    for k in KERNELS:
        if re.search(rf"(?<![A-Za-z_]){k}(?![A-Za-z_])", function_name) or re.search(rf"\d{k}(?:\d|\b|\$|B|E)",
                                                                                       function_name):
            return k
    return None


def parse_ncu_csv(text: str) -> list[dict]:
    """One dict per profiled launch: {"kernel", metric: value (float, base units)} from ncu's ``--csv`` output
    (the lines that are not ncu's own ``==PROF==`` messages or the program's output)."""
    rows = [line for line in text.splitlines() if line.startswith('"')]
    launches: dict[str, dict] = {}
    for rec in csv.DictReader(io.StringIO("\n".join(rows))):
        if rec.get("ID") is None or rec.get("Metric Name") is None:
            continue
        d = launches.setdefault(rec["ID"], {"function": rec.get("Kernel Name", "")})
        try:
            d[rec["Metric Name"]] = float(rec["Metric Value"].replace(",", ""))
        except ValueError:
            pass
    out = []
    for d in launches.values():
        k = kernel_of(d["function"])
        if k is not None:
            out.append({"kernel": k, **{m: d[m] for m in METRICS if m in d}})
    return out


def summarise(launches: list[dict], n: int) -> dict:
    """{kernel: medians over its launches: bytes per particle read, written, total; % of DRAM peak; µs; warps
    active %; registers}."""
    table = {}
    for k in KERNELS:
        rows = [r for r in launches if r["kernel"] == k]
        if not rows:
            continue

        def med(metric, scale=1.0):
            vals = [r[metric] * scale for r in rows if metric in r]
            return statistics.median(vals) if vals else float("nan")

        rd, wr = med("dram__bytes_read.sum", 1.0 / n), med("dram__bytes_write.sum", 1.0 / n)
        table[k] = {"launches": len(rows), "read_B": rd, "written_B": wr, "bytes_per_particle": rd + wr,
                    "dram_pct_peak": med("gpu__dram_throughput.avg.pct_of_peak_sustained_elapsed"),
                    "us": med("gpu__time_duration.sum", 1e-3),
                    "warps_active_pct": med("sm__warps_active.avg.pct_of_peak_sustained_active"),
                    "registers": med("launch__registers_per_thread")}
    for kind, names in STEP.items():
        if all(k in table for k in names):
            table[f"step ({kind})"] = {"bytes_per_particle": sum(table[k]["bytes_per_particle"] for k in names),
                                       "us": sum(table[k]["us"] for k in names)}
    return table


def case_particles(case: str) -> int:
    """The particles a bench/loop_ab.py case's kernels run over: all its scenes' (256 packed scenes of 4096: 2^20)."""
    from bench.loop_ab import EXTRA, JAXMD_CASES

    return JAXMD_CASES[case][0] if case in JAXMD_CASES else EXTRA[case][0] * EXTRA[case][1]


def main(argv=None) -> int:
    from bench import out_dir
    from bench.loop_ab import EXTRA, JAXMD_CASES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", choices=list(JAXMD_CASES) + list(EXTRA),
                    default=["rough-8M-f32", "elastic-8M-f32"])
    ap.add_argument("--variants", nargs="+", default=["default"], help="bench/loop_ab.py variants")
    ap.add_argument("--phi", type=float, default=0.058)
    ap.add_argument("--launch-skip", type=int, default=200)
    ap.add_argument("--launch-count", type=int, default=8)
    ap.add_argument("--steps-scale", type=float, default=0.3, help="of the case's steps (loop_ab --steps-scale)")
    ap.add_argument("--ncu", default="ncu")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    out = out_dir(args.out, "step_bytes")
    regex = "regex:" + "|".join(KERNELS)
    for case in args.cases:
        n = case_particles(case)
        for v in args.variants:
            profiled = "startup" if v == "default" else f"{v}+startup"
            cmd = [args.ncu, "--clock-control", "none", "--kernel-name", regex, "--launch-skip", str(args.launch_skip),
                   "--launch-count", str(args.launch_count), "--metrics", ",".join(METRICS), "--csv",
                   "--print-units", "base", sys.executable, "-m", "bench", "loop_ab", "--cases", case, "--variants",
                   profiled, "--steps-scale", str(args.steps_scale), "--phi", str(args.phi),
                   "--out", str(out / "loop_ab")]
            p = subprocess.run(cmd, cwd=str(ROOT), capture_output=True, text=True,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
            (out / f"ncu-{case}-{v}-phi{args.phi:g}.csv").write_text(p.stdout)
            if p.returncode != 0:
                print(f"{case} {v}: ncu exited {p.returncode}\n{p.stderr[-2000:]}", file=sys.stderr)
                continue
            table = summarise(parse_ncu_csv(p.stdout), n)
            loop = [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]
            print(json.dumps({"case": case, "phi": args.phi, "variant": v, "n": n, "kernels": table,
                              "loop_under_ncu": loop[-1] if loop else None}), flush=True)
            print(f"| {case} φ={args.phi:g} {v} | kernel | B/particle (read + written) | % DRAM peak | µs | "
                  "warps active % | registers |")
            for k, r in table.items():
                if "read_B" in r:
                    print(f"|  | {k} | {r['bytes_per_particle']:.1f} ({r['read_B']:.1f} + {r['written_B']:.1f}) | "
                          f"{r['dram_pct_peak']:.0f} | {r['us']:.0f} | {r['warps_active_pct']:.0f} | "
                          f"{r['registers']:.0f} |")
                else:
                    print(f"|  | {k} | {r['bytes_per_particle']:.1f} |  | {r['us']:.0f} |  |  |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
