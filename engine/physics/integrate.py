"""Translational velocity Verlet (Hidalgo et al. 2013), one particle and one component at a time.

A step is kick(dt/2) - drift(dt) - forces - kick(dt/2); backends fuse the closing half kick with the
next opening one into a single full kick and split it again only where synchronous velocities are
needed (output, checkpoints). The angular velocity of a sphere obeys the same kick (torque / I); its
orientation turns by the exact rotation of the mid-step spin (:func:`engine.physics.rotation.sphere_quat_turn`,
applied lazily by the backends), which is at least as accurate as the Fincham leap-frog of Hidalgo et al. (2013)
(:func:`engine.physics.rotation.fincham_quat_step_space`).
"""

import numba


@numba.njit
def kick(v, f, inv_m, h):
    """v + F/m h: velocity (m/s) after an impulse over h seconds."""
    return v + f * inv_m * h


@numba.njit
def drift_wrap(x, v, dt, box, inv_box):
    """Position after a drift of dt, wrapped into [0, box)."""
    y = x + v * dt
    # = y - box * floor(y / box) for a drift shorter than a box, written with comparisons: math.floor
    # returns an int64 that promotes float32 to float64 (numba-cuda has no np.floor). Compares y with
    # box itself, so a y a rounding below box stays (the floor form could give -1 ulp there).
    if y >= box:
        return y - box
    if y < box - box:
        return y + box
    return y
