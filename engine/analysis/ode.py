"""A small explicit ODE integrator for the mean-field references (engine/analysis/theory.py,
engine/analysis/shear_instability.py).

Dormand & Prince's embedded Runge-Kutta pair of orders 5 and 4 (J. Comput. Appl. Math. 6, 19 (1980); the pair
of Hairer, Norsett & Wanner, Solving ODEs I, §II.5), with the usual step-size control: the step is accepted
when the RMS over components of (y5 - y4) / (atol + rtol max(|y|, |y_new|)) is at most 1, and the next step
is h * clip(0.9 err^(-1/5), 0.2, 5). Steps end exactly on the requested output times, so no dense-output
interpolation enters the result. The systems integrated here are small (1-2 unknowns) and not stiff, so plain
Python floats are used.
"""

from __future__ import annotations

import math

import numpy as np

# Butcher tableau (rows of a), nodes c, fifth-order weights b and the error weights b5 - b4.
_C = (0.0, 1.0 / 5.0, 3.0 / 10.0, 4.0 / 5.0, 8.0 / 9.0, 1.0, 1.0)
_A = (
    (),
    (1.0 / 5.0,),
    (3.0 / 40.0, 9.0 / 40.0),
    (44.0 / 45.0, -56.0 / 15.0, 32.0 / 9.0),
    (19372.0 / 6561.0, -25360.0 / 2187.0, 64448.0 / 6561.0, -212.0 / 729.0),
    (9017.0 / 3168.0, -355.0 / 33.0, 46732.0 / 5247.0, 49.0 / 176.0, -5103.0 / 18656.0),
    (35.0 / 384.0, 0.0, 500.0 / 1113.0, 125.0 / 192.0, -2187.0 / 6784.0, 11.0 / 84.0),
)
_B = _A[6] + (0.0,)
_E = (71.0 / 57600.0, 0.0, -71.0 / 16695.0, 71.0 / 1920.0, -17253.0 / 339200.0, 22.0 / 525.0, -1.0 / 40.0)


def solve(rhs, t_span, y0, t_eval, rtol: float = 1e-10, atol: float = 1e-13, max_steps: int = 1_000_000):
    """y at the times ``t_eval`` of dy/dt = rhs(t, y), y(t_span[0]) = y0, integrated up to t_span[1].

    rhs(t, y) takes a float and a list of floats and returns a sequence of floats. t_eval: times in
    [t_span[0], t_span[1]], in any order. Returns an array of shape (len(y0), len(t_eval)), like
    ``scipy.integrate.solve_ivp(...).y``. Raises RuntimeError when the step size underflows or ``max_steps``
    steps are not enough.
    """
    t0, t1 = float(t_span[0]), float(t_span[1])
    if not t1 >= t0:
        raise ValueError(f"t_span must be increasing, got {t_span}")
    t_eval = np.asarray(t_eval, dtype=float)
    if t_eval.size and (t_eval.min() < t0 or t_eval.max() > t1):
        raise ValueError("t_eval must lie inside t_span")
    y = [float(v) for v in y0]
    n = len(y)
    out = np.empty((n, t_eval.size))
    order = np.argsort(t_eval, kind="stable")
    targets = t_eval[order]
    k = 0
    while k < targets.size and targets[k] == t0:
        out[:, order[k]] = y
        k += 1
    if k == targets.size:
        return out

    def f(t, yy):
        return [float(v) for v in rhs(t, yy)]

    def norm(v, ya, yb):
        return math.sqrt(sum((vi / (atol + rtol * max(abs(a), abs(b)))) ** 2 for vi, a, b in zip(v, ya, yb)) / n)

    t = t0
    k1 = f(t, y)
    # initial step (Hairer, Norsett & Wanner §II.4): h0 from the sizes of y and y', refined by one Euler step
    scale = [atol + rtol * abs(v) for v in y]
    d0 = math.sqrt(sum((v / s) ** 2 for v, s in zip(y, scale)) / n)
    d1 = math.sqrt(sum((v / s) ** 2 for v, s in zip(k1, scale)) / n)
    h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
    h0 = min(h0, t1 - t0)
    y_e = [a + h0 * b for a, b in zip(y, k1)]
    k_e = f(t + h0, y_e)
    d2 = math.sqrt(sum(((b - a) / s) ** 2 for a, b, s in zip(k1, k_e, scale)) / n) / h0
    h1 = max(1e-6, h0 * 1e-3) if max(d1, d2) <= 1e-15 else (0.01 / max(d1, d2)) ** 0.2
    h = min(100.0 * h0, h1, t1 - t0)

    for _ in range(max_steps):
        target = targets[k]
        landing = t + h >= target
        step = target - t if landing else h
        if step <= 1e-15 * max(abs(t), 1.0):
            if landing:          # already there to rounding
                out[:, order[k]] = y
                k += 1
                if k == targets.size:
                    return out
                continue
            raise RuntimeError(f"step size underflow at t = {t}")
        ks = [k1]
        for i in range(1, 7):
            row = _A[i]
            yi = [y[m] + step * sum(row[j] * ks[j][m] for j in range(i)) for m in range(n)]
            ks.append(f(t + _C[i] * step, yi))
        y_new = yi                                      # the seventh stage is evaluated at the fifth-order result
        err = [step * sum(_E[j] * ks[j][m] for j in range(7)) for m in range(n)]
        e = norm(err, y, y_new)
        if e <= 1.0:
            t = target if landing else t + step
            y, k1 = y_new, ks[6]                        # first same as last
            while k < targets.size and targets[k] <= t:
                out[:, order[k]] = y
                k += 1
            if k == targets.size:
                return out
            factor = 5.0 if e == 0.0 else min(5.0, max(0.2, 0.9 * e ** -0.2))
            # a step cut short to land on an output time does not shrink the next one unless its error asks to
            h = step * factor if factor < 1.0 else max(h, step * factor)
        else:
            h = step * max(0.2, 0.9 * e ** -0.2)
    raise RuntimeError(f"no solution within {max_steps} steps")
