"""Rebuilds that leave the particles in place (engine/loops/cuda_rebuild.py ``SORT_DRIFT_CELLS``): a rebuild permutes
the particle arrays into cell order only once they may have drifted half a cell since the last permutation; the
others build the list through the sort's order.

Under the CUDA simulator each case runs with the default and with a permutation at every rebuild
(``SORT_DRIFT_CELLS = 0``): the same trajectory bit for bit (positions, velocities, spins, read back in id order)
and the same list builds, at least three, of which the default permuted fewer (the first always). Cases: rough
float32 with a Coulomb cap (the order lies in the torque's rows), a dense gas whose list's slots grow, rough
spheroids, two packed scenes of smooth spheres (scene-major cells). The interval itself is checked on the host."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tests.cudasim import run_children

SCRIPT = r'''
import sys
from tests.cudasim import fast_block_polling, kept_ensembles
fast_block_polling()
import tempfile
from pathlib import Path
import h5py, numpy as np
import engine.loops.cuda_ensemble as ens
import engine.loops.cuda_rebuild as rb
from engine import run, run_ensemble
from engine.setup.spec import SimulationSpec

ens.MULTISTEP = False
case = sys.argv[1]
if case == "dense-grows":
    rb.HIST_MARGIN = 0     # the first list holds N slots: the dense gas's rows outgrow them at the first build
    rb.SORT_DRIFT_CELLS = 0.15  # its cells of 3 radii, its skin of 0.4: a permutation every second rebuild
default = rb.SORT_DRIFT_CELLS
kept = kept_ensembles()

# 40 spheres at phi = 0.15 with a skin of 0.1 radii unless the case says otherwise
base = dict(n_particles=40, volume_fraction=0.15, e_n=0.8, thermalization=0.0, snapshots=2, backend="cuda",
            t_end=1.6e-3, output_interval=4e-4, velocity_rms=12.0, verlet_skin=0.1, seed=4, precision="float64")
kw = {"rough-f32-coulomb": dict(precision="float32", e_t=0.8, friction=0.3),
      "dense-grows": dict(e_t=0.8, volume_fraction=0.35, verlet_skin=0.4, n_particles=64, velocity_rms=6.0, t_end=1e-2),
      "spheroids": dict(e_t=0.8, shape="ellipsoid", elongation=1.5, volume_fraction=0.1, velocity_rms=10.0,
                        verlet_skin=0.2),
      "packed-smooth": dict(e_t=-1.0)}[case]
DATA = ("position", "velocity", "angular_velocity")
out = {}
for drift in (default, 0.0):
    rb.SORT_DRIFT_CELLS = drift
    kept.clear()
    d = Path(tempfile.mkdtemp())
    if case == "packed-smooth":
        specs = [SimulationSpec(**{**base, **kw, "seed": s}) for s in (4, 5)]
        got = run_ensemble(specs, [d / "a.h5", d / "b.h5"], backend="cuda")
        files = [g.output for g in got]
    else:
        files = [run(SimulationSpec(**{**base, **kw}), d / "x.h5", backend="cuda").output]
    (e,) = kept
    data = []
    for path in files:
        with h5py.File(path) as f:
            data += [f[f"particles/all/{k}/value"][...] for k in DATA]
    out[drift] = (data, e.builds, e.sorts, e._sort_interval())
(a, builds, sorts, interval), (b, builds_ref, sorts_ref, _) = out[default], out[0.0]
assert builds == builds_ref and builds >= 3, out
assert sorts_ref == builds_ref and 1 <= sorts < builds and interval > 1, (sorts, builds, interval)
assert sorts == 1 + (builds - 1) // interval, (sorts, builds, interval)
if case == "dense-grows":
    assert sorts >= 2, (sorts, builds)     # permuted again after rebuilds that were not
for x, y in zip(a, b):
    assert np.array_equal(x, y), case
print("SORT-OK", case, builds, sorts, interval)
'''

CASES = ("rough-f32-coulomb", "dense-grows", "spheroids", "packed-smooth")


@pytest.mark.heavy      # ~1 min of CUDA simulator (eight short runs)
def test_rebuilds_without_a_permutation_keep_the_trajectory():
    got = run_children({c: ["-c", SCRIPT, c] for c in CASES}, timeout=1200)
    for case, (rc, out, err) in got.items():
        assert rc == 0 and "SORT-OK" in out, (case, out[-3000:] + err[-3000:])


def _lists(skins, cells, multigrid=False):
    """A stand-in for the ensemble's list part: scenes of ``skins`` (m) and cell edges ``cells`` (m)."""
    from engine.loops import cuda_kernels as K

    spi = np.zeros((len(cells), K.NI), np.int32)
    spi[:, K.I_NC] = 10
    return SimpleNamespace(multigrid=multigrid, contact=[SimpleNamespace(skin=s) for s in skins],
                           box=10.0 * np.asarray(cells, float), spi_h=spi, sorts=0, _builds_since_sort=None)


def test_sort_interval_counts_half_skins_per_drift():
    from engine.loops import cuda_rebuild as rb
    from engine.loops.cuda_rebuild import ListBuilds

    drift = rb.SORT_DRIFT_CELLS
    assert drift > 0
    # a cell of 2.03 radii, a skin of 0.03 radii: floor(drift * 2.03 / 0.015) rebuilds a permutation
    assert ListBuilds._sort_interval(_lists([0.03], [2.03])) == int(np.floor(drift * 2.03 / 0.015))
    # the scene that drifts furthest in cells sets it; a thick skin permutes at every rebuild
    assert ListBuilds._sort_interval(_lists([0.03, 0.3], [2.03, 2.3])) == max(1, int(np.floor(drift * 2.3 / 0.15)))
    assert ListBuilds._sort_interval(_lists([4.0], [6.0])) == 1
    assert ListBuilds._sort_interval(_lists([0.03], [2.03], multigrid=True)) == 1
    assert ListBuilds._sort_interval(_lists([0.0], [2.0])) == 1


def test_sort_due_permutes_the_first_build_and_then_every_interval(monkeypatch):
    from engine.loops import cuda_rebuild as rb
    from engine.loops.cuda_rebuild import ListBuilds

    lists = _lists([0.1], [2.1])
    lists._sort_interval = lambda: 3
    due = [ListBuilds._sort_due(lists) for _ in range(8)]
    assert due == [True, False, False, True, False, False, True, False] and lists.sorts == 3
    monkeypatch.setattr(rb, "SORT_DRIFT_CELLS", 0.0)
    lists = _lists([0.1], [2.1])
    lists._sort_interval = lambda: ListBuilds._sort_interval(lists)
    assert all(ListBuilds._sort_due(lists) for _ in range(4)) and lists.sorts == 4
