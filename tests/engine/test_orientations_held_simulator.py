"""A sphere ensemble that neither tracks orientations nor has its state read holds no orientations on the device
(engine/shapes/sphere/cuda_backend.py ``orientations_held``), under the Numba CUDA simulator: the same positions,
velocities, spins and observables bit for bit as the ensemble that holds them (so does one whose state is read but
whose scenes want no orientations), a start drawn on the device included (its orientation stream left undrawn, the
others the same), the identity quaternion where the state is asked for anyway, and a clear error where orientations
would be switched on. Runs in a simulator child (tests/cudasim.py)."""

import sys
from pathlib import Path

import numpy as np

from tests.cudasim import run_children

ROOT = Path(__file__).resolve().parents[2]


def _child() -> None:
    from engine.backends.base import SphereSystem
    from engine.backends.cuda import CudaEnsemble
    from engine.loops import cuda_ensemble
    from engine.setup.scene import StartDraw
    from tests.engine.test_cuda_simulator import contact, tiny_system
    from tests.engine.test_device_start_simulator import _streams

    n, box, r = 60, 1.2, 0.05
    drawn = SphereSystem(box_length=box, position=None, velocity=None, angular_velocity=None, orientation=None,
                         radius=np.full(n, r), mass=np.full(n, 1.0), inertia=np.full(n, 0.4 * r * r),
                         draw=StartDraw.of(n, 5, _streams(), box, r))
    c = contact(skin=0.01, orientation=False)
    for multistep in (True, False):     # the many-steps loop of small scenes and the per-phase loop of large ones
        cuda_ensemble.MULTISTEP = multistep
        ens = {held: CudaEnsemble([tiny_system(), drawn], [c, c], reads_state=held) for held in (False, True)}
        # state read, but no scene wants orientations (the spec's orientations = false): none held either
        ens["read"] = CudaEnsemble([tiny_system(), drawn], [c, c], reads_state=True, orientations=False)
        assert not ens[False].orientations_held and ens[True].orientations_held
        assert not ens["read"].orientations_held and ens["read"].quat.size == 4
        assert ens[False].quat.size == 4 and ens[True].quat.shape == (4, tiny_system().n + n)
        for e in ens.values():
            assert e.multistep == multistep
            e.advance(40)
        a, b, r = ens[False], ens[True], ens["read"]
        assert a.builds == b.builds == r.builds >= 2, (a.builds, b.builds, r.builds)
        for k in (0, 1):
            sa, sb, sr = a.state(k), b.state(k), r.state(k)
            for key in ("position", "velocity", "angular_velocity"):
                assert np.array_equal(sa[key], sb[key]) and np.array_equal(sr[key], sb[key]), (multistep, k, key)
            identity = np.zeros((sa["position"].shape[0], 4))
            identity[:, 0] = 1.0
            assert np.array_equal(sa["orientation"], identity), k
        oa, ob = a.observe(), b.observe()
        assert oa == ob, (multistep, oa, ob)
    try:
        a.set_contact(0, contact(skin=0.01, orientation=True))
    except RuntimeError as exc:
        assert "orientations switched on" in str(exc), exc
    else:
        raise AssertionError("orientations switched on in an ensemble without them")
    print("held ok")


def test_an_ensemble_without_orientations_runs_the_same_scenes():
    here = Path(__file__).resolve()
    (rc, out, err), = run_children({"held": [here]}, timeout=600).values()
    assert rc == 0 and "held ok" in out, f"{out}\n{err[-3000:]}"


if __name__ == "__main__":
    from tests.cudasim import fast_block_polling

    sys.path.insert(0, str(ROOT))
    fast_block_polling()
    _child()
