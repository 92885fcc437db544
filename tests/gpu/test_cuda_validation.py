"""Homogeneous cooling of rough spheres on the GPU backend against Luding's mean-field ODE (Hidalgo et al. 2013)."""

import numpy as np
import pytest

from engine.backends.base import cuda_available

pytestmark = pytest.mark.skipif(not cuda_available(), reason="needs a CUDA GPU")


@pytest.mark.parametrize("e_n,e_t", [(0.9, 0.5), (0.8, -0.5)])
def test_cooling_matches_luding_ode_on_gpu(tmp_path, e_n, e_t):
    import h5py

    from engine.setup.params import Q_SPHERE, derive
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec
    from engine.analysis.theory import collision_g, luding_ode

    spec = SimulationSpec(n_particles=32768, volume_fraction=0.05, e_n=e_n, e_t=e_t, t_end=1.0, seed=5,
                          snapshots=0, backend="cuda")
    p = derive(spec)
    g = collision_g(p.radius, p.number_density, p.mass, spec.volume_fraction)
    t_end = 2.5 / (2.0 / 3.0 * g * np.sqrt(p.temperature0))
    spec = spec.model_copy(update={"t_end": t_end})
    summary = run(spec, tmp_path / "cool.h5")
    assert summary.backend == "cuda"
    with h5py.File(summary.output, "r") as f:
        t = f["observables/temperature_translational/time"][:]
        tt = f["observables/temperature_translational/value"][:]
        rr = f["observables/temperature_rotational/value"][:]
    t0, r0 = tt[0], rr[0]
    tau = 2.0 / 3.0 * g * np.sqrt(t0) * t
    t_ode, r_ode = luding_ode(e_n, e_t, tau, t0=1.0, r0=r0 / t0, q=Q_SPHERE)
    err_t = np.max(np.abs(tt / t0 / t_ode - 1))
    err_r = np.max(np.abs(rr / t0 / r_ode - 1))
    print(f"\nGPU e_n={e_n} e_t={e_t}: tau_end {tau[-1]:.2f}, T/T0 {tt[-1] / t0:.4f} vs ODE {t_ode[-1]:.4f}, "
          f"R/T0 {rr[-1] / t0:.4f} vs ODE {r_ode[-1]:.4f}; max rel err T {err_t:.3f} R {err_r:.3f}; "
          f"Cundall {summary.cundall:.3g}")
    assert err_t < 0.05 and err_r < 0.05
