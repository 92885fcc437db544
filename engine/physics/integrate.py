"""Translational velocity Verlet (paper 001), one particle and one component at a time.

A step is kick(dt/2) - drift(dt) - forces - kick(dt/2); backends fuse the closing half kick with the
next opening one into a single full kick and split it again only where synchronous velocities are
needed (output, checkpoints). The angular velocity of a sphere obeys the same kick (torque / I), which
together with :func:`engine.physics.rotation.fincham_quat_step_space` is Fincham's leap-frog.
"""

import math

import numba


@numba.njit
def kick(v, f, inv_m, h):
    """v + F/m h: velocity (m/s) after an impulse over h seconds."""
    return v + f * inv_m * h


@numba.njit
def drift_wrap(x, v, dt, box, inv_box):
    """Position after a drift of dt, wrapped into [0, box)."""
    y = x + v * dt
    return y - box * math.floor(y * inv_box)
