"""Smoke tests of bench/vs_lammps.py: the LAMMPS input carries demq's contact model, and (only when ``lmp``
is installed) a tiny side-by-side run completes with both codes integrating the same gas."""

import math
import os
import shutil

import numpy as np
import pytest

from bench import vs_lammps
from engine.setup.params import derive
from engine.setup.scene import initial_spheres


def _pair_style(text):
    (line,) = [ln for ln in text.splitlines() if ln.startswith("pair_style")]
    _, style, kn, kt, gn, gt, xmu, damp = line.split()
    return style, float(kn), float(kt), float(gn), float(gt), float(xmu), int(damp)


@pytest.mark.parametrize("n, phi", [(4096, 0.008), (32768, 0.058)])
def test_lammps_input_matches_demq_parameters(n, phi):
    spec = vs_lammps.scene_spec(n, phi, steps=1234)
    p = derive(spec)
    assert spec.velocity_rms == 3.0 and spec.e_n == 0.8 and spec.e_t == 0.8 and spec.friction is None
    assert p.radius == pytest.approx(derive(vs_lammps.SimulationSpec()).radius, rel=1e-12)  # default radius kept
    assert p.n_steps == 1234 and p.n_thermalization_steps == 0
    text = vs_lammps.lammps_input(vs_lammps.lammps_params(spec), 1234)
    style, kn, kt, gn, gt, xmu, damp = _pair_style(text)
    assert style == "gran/hooke/history"
    assert kn == 1.0e8 == p.k_n
    # Hidalgo et al. (2013) Eq. 4, written out independently of params.py
    assert kt == pytest.approx(1.0e8 * (2.0 / 7.0) * (math.acos(-0.8) / math.pi) ** 2, rel=1e-14)
    # LAMMPS damps with m_eff * gamma_n: m_eff = m/2 for equal spheres of the data file's density and size
    mass = 2000.0 * 4.0 / 3.0 * math.pi * p.radius**3
    m_eff = mass / 2.0
    assert gn * m_eff == pytest.approx(p.gamma_n, rel=1e-12)
    # and that oscillator m_eff x'' + m_eff gn x' + kn x = 0 restitutes e_n = 0.8 (rule (a): ends at x = 0)
    omega = math.sqrt(kn / m_eff - gn**2 / 4.0)
    assert math.exp(-gn / 2.0 * math.pi / omega) == pytest.approx(0.8, rel=1e-12)
    assert gt == 0.0 and damp == 0 and xmu == 1.0e4   # no tangential damping; Coulomb limit effectively off
    assert f"timestep {p.dt!r}" in text
    assert p.dt == pytest.approx(math.pi * math.sqrt(m_eff / kn) / 50.0, rel=1e-12)
    assert f"neighbor {p.radius!r} bin" in text              # skin of one radius
    assert "neigh_modify delay 0 every 10 check yes" in text
    assert "fix 1 all nve/sphere" in text and "run 1234" in text and "units si" in text


def test_data_file_is_demq_start(tmp_path):
    spec = vs_lammps.scene_spec(300, 0.05, steps=10)
    p = derive(spec)
    system = initial_spheres(spec, p)
    vs_lammps.write_data(tmp_path / "data.lmp", system)
    lines = (tmp_path / "data.lmp").read_text().splitlines()
    assert "300 atoms" in lines
    a = lines.index("Atoms # sphere")
    v = lines.index("Velocities")
    atoms = np.array([[float(x) for x in ln.split()] for ln in lines[a + 2:v - 1]])
    vels = np.array([[float(x) for x in ln.split()] for ln in lines[v + 2:] if ln.strip()])
    assert atoms.shape == (300, 7) and vels.shape == (300, 7)
    assert np.allclose(atoms[:, 2], 2.0 * p.radius, rtol=1e-15) and np.allclose(atoms[:, 3], 2000.0, rtol=1e-12)
    L = spec.box_length
    assert np.all(atoms[:, 4:7] >= 0.0) and np.all(atoms[:, 4:7] < L)
    assert np.allclose(atoms[:, 4:7], system.position % L, rtol=0, atol=1e-15)
    assert np.array_equal(vels[:, 1:4], system.velocity) and np.array_equal(vels[:, 4:7], system.angular_velocity)


@pytest.mark.skipif(shutil.which("lmp") is None, reason="LAMMPS (lmp) not installed")
def test_tiny_side_by_side(tmp_path):
    row = vs_lammps.compare(n=400, phi=0.3, steps=3000, threads=1, skin_radii=1.0, out_dir=tmp_path, pairs=2)
    assert row["start"] == "random" and row["lammps"]["available"] and row["pairs"] == 2
    assert [d["steps"] for d in row["demq_runs"]] == [3000, 3000]
    demq = [d["cundall_loop"] for d in row["demq_runs"]]
    lmp = [m["cundall_loop"] for m in row["lammps_runs"]]
    assert min(demq) > 0 and min(lmp) > 0
    assert row["ratio_loop"] == pytest.approx((demq[0] / lmp[0] + demq[1] / lmp[1]) / 2)   # median of two
    assert row["demq_spread"] == pytest.approx(max(demq) / min(demq) - 1)
    assert (tmp_path / "in.n400_t1.lammps").exists() and (tmp_path / "log.n400_t1.lammps").exists()
    # the pairs repeat the same run: demq's end state is the same bits each time
    d, d2 = row["demq_runs"]
    assert d["ke_translational_end"] == d2["ke_translational_end"]
    # same start, same contact model: the dissipated energy agrees (different integrators and list
    # schedules move collisions by O(dt^2), so energies agree to far better than the 2 % asked here)
    m = row["lammps_runs"][0]
    e0 = 400 * 0.5 * (2000.0 * 4.0 / 3.0 * math.pi * row["lammps_params"]["radius"] ** 3) * 9.0
    for key in ("ke_translational_end", "ke_rotational_end"):
        assert d[key] == pytest.approx(m[key], rel=0.02)
    assert d["ke_translational_end"] < 0.999 * e0            # the gas did collide and dissipate
    assert "| 400 |" in vs_lammps.table([row])
    # what the machine did meanwhile: each run's CPU seconds (the child's, for LAMMPS) and the host's steal
    for r in row["demq_runs"] + row["lammps_runs"]:
        assert 0 < r["cpu_s"] < 4 * r["wall_s"] and (r["steal_s"] is None or r["steal_s"] >= 0), r


def test_host_steal_reads_proc_stat(tmp_path, monkeypatch):
    """The steal field is the eighth number of /proc/stat's first line (after user, nice, system, idle, iowait, irq,
    softirq), in clock ticks; no such field gives None."""
    stat = tmp_path / "stat"
    stat.write_text("cpu  10 0 20 30000 5 0 1 250 0 0\ncpu0 5 0 10 15000 2 0 0 125 0 0\n")
    real_path = vs_lammps.Path
    monkeypatch.setattr(vs_lammps, "Path", lambda p: stat if p == "/proc/stat" else real_path(p))
    assert vs_lammps.host_steal_s() == pytest.approx(250 / vs_lammps.os.sysconf("SC_CLK_TCK"))
    stat.write_text("cpu  10 0 20 30000\n")
    assert vs_lammps.host_steal_s() is None


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="the co-runner needs two CPUs")
def test_co_runner_streams_on_the_other_cpus_and_ends_with_the_comparison():
    allowed = os.sched_getaffinity(0)
    with vs_lammps.co_runner(8) as proc:
        assert proc.poll() is None                                      # streaming meanwhile
        ours, theirs = os.sched_getaffinity(0), os.sched_getaffinity(proc.pid)
        assert len(ours) == 1 and ours | theirs == allowed and not ours & theirs
    assert proc.poll() is not None and os.sched_getaffinity(0) == allowed
