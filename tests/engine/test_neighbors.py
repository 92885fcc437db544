"""Verlet lists (Skorych & Dosta 2022): complete, rebuilt on the L_v/2 rule, tangential springs carried over."""

import numpy as np

from engine.shapes.sphere.cpu_backend import CpuBackend
from tests.engine.scenes import gas


def _brute_contacts(pos, radius, box):
    d = pos[:, None, :] - pos[None, :, :]
    d -= box * np.round(d / box)
    r = np.sqrt((d**2).sum(-1))
    s = radius[:, None] + radius[None, :]
    np.fill_diagonal(r, np.inf)
    return {(i, j) for i, j in zip(*np.nonzero(r < s))}


def test_list_holds_every_contact_between_rebuilds():
    system, params = gas(n=128, phi=0.3, v_rms=0.2, skin=0.1)
    be = CpuBackend(system, params)
    for _ in range(20):
        be.advance(37)
        listed = {(i, int(be.nbr[i, k])) for i in range(be.n) for k in range(be.nn[i])}
        assert _brute_contacts(be.pos, be.radius, be.box) <= listed
    assert be.builds > 3


def test_springs_survive_rebuilds():
    """The same scene with a thin skin (many rebuilds) and a thick one (few) gives the same trajectory."""
    runs = []
    for skin in (0.05, 1.0):
        system, params = gas(n=64, phi=0.3, v_rms=0.05, skin=skin, e_n=0.7, e_t=0.5)
        be = CpuBackend(system, params)
        be.advance(1500)
        runs.append((be.pos.copy(), be.omega.copy(), be.builds))
    (p1, w1, b1), (p2, w2, b2) = runs
    assert b1 > 3 * b2
    # only the summation order differs (rounding); a lost spring would change spins at O(1)
    assert np.abs(w1 - w2).max() < 1e-8 * np.abs(w1).max()
    assert np.abs(p1 - p2).max() < 1e-10
