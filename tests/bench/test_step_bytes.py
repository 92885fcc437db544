"""bench/step_bytes.py's reading of Nsight Compute's CSV (no GPU, no ncu: a CSV in ncu's ``--csv --print-units base``
layout, as an H200 run printed it, with made-up numbers)."""

from __future__ import annotations

import math

from bench.step_bytes import case_particles, kernel_of, parse_ncu_csv, summarise

HEADER = ('"ID","Process ID","Process Name","Host Name","Kernel Name","Context","Stream","Block Size","Grid Size",'
          '"Device","CC","Section Name","Metric Name","Metric Unit","Metric Value"')


def _row(launch: int, kernel: str, metric: str, value: str) -> str:
    name = f"{kernel}[v42,cw51cXTLSUwv1sDUaKthq_3d](long long, Array<float, 2, C, mutable, aligned>)"
    return (f'"{launch}","1242","python3.12","127.0.0.1","{name}","1","13","(256, 1, 1)","(528, 1, 1)","0","9.0",'
            f'"Command line profiler metrics","{metric}","byte","{value}"')


def _launch(launch: int, kernel: str, read: float, written: float, ns: float, pct: float) -> list[str]:
    return [_row(launch, kernel, "dram__bytes_read.sum", f"{read:,.0f}"),
            _row(launch, kernel, "dram__bytes_write.sum", f"{written:,.0f}"),
            _row(launch, kernel, "gpu__time_duration.sum", f"{ns:.0f}"),
            _row(launch, kernel, "gpu__dram_throughput.avg.pct_of_peak_sustained_elapsed", f"{pct}"),
            _row(launch, kernel, "launch__registers_per_thread", "80")]


def test_kernel_names_mangled_and_demangled():
    assert kernel_of("_ZN6cudapy6engine5loops9cuda_loop5_make12_3clocals_3e6forcesB3v12E") == "forces"
    assert kernel_of("_ZN6cudapy6engine5loops9cuda_loop5_make12_3clocals_3e17forces_kick_driftB3v1") == \
        "forces_kick_drift"
    assert kernel_of("forces_observe[v42,cw51](long long)") == "forces_observe"
    assert kernel_of("kick_drift[v22,cw51](long long)") == "kick_drift"
    assert kernel_of("half_kick[v3](long long)") is None
    assert kernel_of("fill_i32[v1](Array<int>)") is None


def test_bytes_per_particle_step_are_the_medians_over_launches_and_the_step_sums_its_kernels():
    n = 1000
    lines = ["==PROF== Connected to process 1242", '{"case": "rough-8M-f32"}', HEADER]
    lines += _launch(0, "forces", 40_000, 10_000, 400_000, 20.0)
    lines += _launch(1, "kick_drift", 30_000, 12_000, 100_000, 50.0)
    lines += _launch(2, "forces", 44_000, 10_000, 420_000, 22.0)
    lines += _launch(3, "kick_drift", 30_000, 12_000, 110_000, 52.0)
    lines += _launch(4, "forces", 42_000, 10_000, 410_000, 21.0)
    lines += _launch(5, "half_kick", 1e9, 1e9, 1.0, 1.0)     # not a kernel of the step: left out
    launches = parse_ncu_csv("\n".join(lines))
    assert [x["kernel"] for x in launches] == ["forces", "kick_drift", "forces", "kick_drift", "forces"]
    table = summarise(launches, n)
    assert table["forces"]["launches"] == 3
    assert math.isclose(table["forces"]["read_B"], 42.0) and math.isclose(table["forces"]["written_B"], 10.0)
    assert math.isclose(table["forces"]["bytes_per_particle"], 52.0)
    assert math.isclose(table["forces"]["us"], 410.0) and math.isclose(table["forces"]["dram_pct_peak"], 21.0)
    assert math.isclose(table["kick_drift"]["bytes_per_particle"], 42.0)
    assert math.isclose(table["step (two launches)"]["bytes_per_particle"], 94.0)
    assert "step (fused)" not in table


def test_a_packed_case_counts_every_scenes_particles():
    """Bytes per particle of a packed case are over the whole ensemble the kernels run on."""
    assert case_particles("packed-rough-256x4096-f64") == 256 * 4096 == case_particles("rough-1M-f64")
    assert case_particles("rough-8M-f32") == 8_388_608
