"""Single-source physics: small @numba.njit functions on scalars, called by every backend.

Keep these plain ``@numba.njit`` (no signature, no parallel, no cache flag): the CUDA backend calls
the same functions from its kernels, and options given here would be copied to the CUDA
compilation. Optional parameters that switch physics off are passed as ``None`` so that Numba prunes
the branch at compile time (``if k_t is None``) instead of testing it in the hot loop.
No float literals in arithmetic: a ``half`` argument (0.5 in the working precision) keeps float32
runs in float32 arithmetic.
"""
