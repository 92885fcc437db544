"""Run status codes shared by every backend's time loop, and the error each failure status becomes.

A compiled loop returns one of OK, BAD_VALUE (non-finite position or velocity), OVERLAP (overlap above
``overlap_limit`` radii) or OVERFLOW (a neighbour list outgrew its stride: grow and resume); the host side
turns BAD_VALUE and OVERLAP into an :class:`engine.errors.InstabilityError` naming the step, the particle
and the likely cause (:func:`instability_error`). No backend owns this module; every backend may import it.
"""

from __future__ import annotations

from engine.errors import InstabilityError

OK, BAD_VALUE, OVERLAP, OVERFLOW = 0, 1, 2, 3


def instability_error(status: int, step: int, who: int, value: float, backend) -> InstabilityError:
    """The error for a BAD_VALUE or OVERLAP status at ``step`` and particle ``who`` (``value``: the overlap
    in radii); ``backend`` supplies ``dt`` (s) and ``overlap_limit`` (radii) for the message."""
    if status == BAD_VALUE:
        msg = (f"non-finite position or velocity of particle {who} at step {step}: the run blew up; "
               f"likely cause: a time step too large for the contact (dt = {float(backend.dt):.3g} s) "
               f"or overlapping particles at the start")
    else:
        msg = (f"overlap of {value:.3g} radii at particle {who} at step {step} exceeds the limit "
               f"{backend.overlap_limit:g}: likely cause: impact speeds too high for the stiffness "
               f"(lower velocity_rms or raise stiffness) or a time step too large (dt = {float(backend.dt):.3g} s)")
    return InstabilityError(msg, step=step, particle=who)
