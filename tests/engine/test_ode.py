"""engine/analysis/ode.py (Dormand-Prince 5(4)) against closed forms, and Luding's ODE (engine/analysis/theory.py)
solved by it against its exact solution in collision time."""

import math

import numpy as np
import pytest

from engine.analysis.ode import solve
from engine.analysis.theory import luding_coefficients, luding_ode


def test_a_damped_rotation_matches_its_closed_form():
    # y' = [[-a, -w], [w, -a]] y: y(t) = e^(-a t) (cos w t, sin w t) from (1, 0)
    a, w = 0.3, 2.0
    t = np.linspace(0.0, 20.0, 41)
    y = solve(lambda _, v: [-a * v[0] - w * v[1], w * v[0] - a * v[1]], (0.0, 20.0), [1.0, 0.0], t,
              rtol=1e-10, atol=1e-14)
    exact = np.exp(-a * t) * np.stack([np.cos(w * t), np.sin(w * t)])
    # local error control at rtol 1e-10 over ~6 turns: a global error below ~1e-9 of the amplitude
    assert (np.abs(y - exact) / np.exp(-a * t)).max() < 5e-9


def test_outputs_in_any_order_at_the_requested_times():
    t = np.array([3.0, 0.0, 1.0, 3.0, 2.5])
    y = solve(lambda _, v: [-v[0]], (0.0, 3.0), [2.0], t)
    assert y.shape == (1, 5) and y[0, 1] == 2.0                       # the initial value, untouched
    assert y[0] == pytest.approx(2.0 * np.exp(-t), rel=1e-9)
    assert y[0, 0] == y[0, 3]


def test_bad_spans_are_refused():
    with pytest.raises(ValueError, match="t_span"):
        solve(lambda _, v: v, (1.0, 0.0), [1.0], [0.5])
    with pytest.raises(ValueError, match="t_eval"):
        solve(lambda _, v: v, (0.0, 1.0), [1.0], [1.5])


def test_smooth_spheres_follow_haff_exactly():
    # e_t = -1: eta = 0, so B = C = 0: dT/dtau = -A T^(3/2) gives T = (1 + A tau/2)^-2 and R stays R(0)
    e_n = 0.8
    a = luding_coefficients(e_n, -1.0)[0]
    tau = np.concatenate([[0.0], np.geomspace(1e-3, 1e4, 200)])
    t, r = luding_ode(e_n, -1.0, tau, 1.0, 0.4)
    # rtol 1e-10 per step, over the ~10^3 steps to tau = 10^4 (T falls by 10^6): below ~1e-8
    assert t == pytest.approx((1.0 + 0.5 * a * tau) ** -2, rel=2e-8)
    assert r == pytest.approx(np.full_like(tau, 0.4), rel=1e-12)


@pytest.mark.parametrize("e_n,e_t,r0", [(0.9, 0.9, 1.0), (0.6, 0.0, 0.2), (0.95, -0.5, 2.0), (0.7, 1.0, 1.0)])
def test_rough_spheres_match_the_exact_solution_in_collision_time(e_n, e_t, r0):
    # per collision (s = (3/4) int sqrt(T) dtau) the equations are linear with constant coefficients:
    # d(T, R)/ds = (4/3) [[-A, B], [B, -C]] (T, R), solved by the eigenvectors of that symmetric matrix;
    # tau(s) = (4/3) int_0^s T^(-1/2) ds' by Gauss-Legendre quadrature (16 nodes on each of 4000 panels)
    a, b, c = luding_coefficients(e_n, e_t)
    lam, vec = np.linalg.eigh(4.0 / 3.0 * np.array([[-a, b], [b, -c]]))
    coef = vec.T @ np.array([1.0, r0])

    def state(s):
        return vec @ (coef[:, None] * np.exp(np.outer(lam, s)))

    s_end = 30.0
    edges = np.linspace(0.0, s_end, 4001)
    nodes, weights = np.polynomial.legendre.leggauss(16)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[1:] + edges[:-1])
    pts = (mid[:, None] + half[:, None] * nodes[None, :]).ravel()
    integrand = (4.0 / 3.0 / np.sqrt(state(pts)[0])).reshape(len(mid), 16)
    tau_edges = np.concatenate([[0.0], np.cumsum(half * (integrand @ weights))])
    keep = slice(0, None, 100)                                         # 41 checkpoints from s = 0 to 30
    t, r = luding_ode(e_n, e_t, tau_edges[keep], 1.0, r0)
    exact = state(edges[keep])
    # rtol 1e-10 per step; T falls by up to ~10^4 over the span: relative error ~1e-10, below 2e-9
    assert t == pytest.approx(exact[0], rel=2e-9)
    assert r == pytest.approx(exact[1], rel=2e-9)


@pytest.mark.heavy
@pytest.mark.parametrize("e_n,e_t", [(0.9, 0.9), (0.5, -0.5), (0.99, 0.0), (0.7, 1.0)])
def test_luding_ode_agrees_with_scipy_lsoda(e_n, e_t):
    """Against scipy's LSODA at the same tolerances, which engine/analysis/theory.py used before (the reference
    extra)."""
    integrate = pytest.importorskip("scipy.integrate", reason="scipy (pip install '.[reference]')")
    coeffs = luding_coefficients(e_n, e_t)
    tau = np.concatenate([[0.0], np.geomspace(1e-3, 1e4, 300)])

    def rhs(_, y):
        freq = 0.75 * math.sqrt(max(y[0], 0.0))
        return [freq * 4.0 / 3.0 * (-coeffs[0] * y[0] + coeffs[1] * y[1]),
                freq * 4.0 / 3.0 * (coeffs[1] * y[0] - coeffs[2] * y[1])]

    ref = integrate.solve_ivp(rhs, (0.0, tau[-1]), [1.0, 1.0], method="LSODA", t_eval=tau,
                              rtol=1e-10, atol=1e-13).y
    t, r = luding_ode(e_n, e_t, tau)
    # both integrators at rtol 1e-10: they differ by their global errors, ~1e-8
    assert t == pytest.approx(ref[0], rel=1e-7)
    assert r == pytest.approx(ref[1], rel=1e-7)
