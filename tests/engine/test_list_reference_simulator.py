"""The CUDA list's reference positions x_ref (engine/loops/cuda_memory.py ``xref_dtype``, ``xref_margin``): float32
beside float64 positions where their rounding is small against the skin, with the Verlet rule's limit L_v / 2 less
the rounding's bound, so that a displacement measured against the rounded x_ref below the rule's limit leaves the
true one below L_v / 2; the positions' own type elsewhere."""

from __future__ import annotations

import math

import numpy as np

from tests.cudasim import run_children

SCRIPT = r'''
import dataclasses
import json
import math
from tests.cudasim import fast_block_polling
fast_block_polling()
import numpy as np
from engine.loops import cuda_kernels as K
from engine.backends.cuda import CudaEnsemble
from engine.setup.params import derive
from engine.setup.scene import initial_spheres
from engine.driver.simulate import contact_params
from engine.setup.spec import SimulationSpec

out = {}
for precision in ("float64", "mixed", "float32"):
    spec = SimulationSpec(n_particles=64, volume_fraction=0.1, e_n=0.8, e_t=0.8, seed=4, thermalization=0.0,
                          precision=precision)
    p = derive(spec)
    sy, c = initial_spheres(spec, p), contact_params(spec, p, thermalization=False)
    ens = CudaEnsemble([sy], [c])
    # right after the first build x_ref is the rounded copy of the positions
    pos, xr = ens.pos.copy_to_host().astype(np.float64), ens.x_ref.copy_to_host().astype(np.float64)
    gap = float(np.sqrt(((pos - xr) ** 2).sum(axis=0)).max())
    failed = ens.advance(30)
    assert not failed, failed
    if precision == "float64":      # a skin the reference's rounding would swallow is refused, the scene unchanged
        try:
            ens.set_contact(0, dataclasses.replace(c, skin=1e-9 * float(sy.box_length)))
            raise AssertionError("a skin below the reference's rounding was accepted")
        except ValueError as e:
            assert "verlet_skin" in str(e) and ens.contact[0] is c, e
    out[precision] = dict(xref=ens.x_ref.dtype.str, lim2inv=float(ens.spf_h[0, K.F_LIM2INV]), skin=float(ens.spd_h[0, K.D_SKIN]),
                          box=float(sy.box_length), gap=gap, builds=ens.builds, late=ens.late_rebuilds)
print("XREF-OK", json.dumps(out))
'''


def test_the_float32_list_reference_keeps_the_verlet_rule():
    import json

    rc, out, err = run_children({"run": ["-c", SCRIPT]}, timeout=900)["run"]
    assert rc == 0 and "XREF-OK" in out, out[-3000:] + err[-3000:]
    got = json.loads(out.split("XREF-OK", 1)[1])
    for precision, g in got.items():
        assert g["xref"] == "<f4", precision
        float32_beside_float64 = precision != "float32"
        margin = math.sqrt(3.0) * 2.0 ** -24 * g["box"] if float32_beside_float64 else 0.0
        # the rule's limit is L_v / 2 less the rounding's bound (exactly L_v / 2 where x_ref is the positions' type)
        assert g["lim2inv"] == 1.0 / (0.5 * g["skin"] - margin) ** 2, (precision, g)
        # and the bound holds: no rounded reference lies further from its position than the margin
        assert g["gap"] <= margin, (precision, g)
        assert (g["gap"] > 0.0) == float32_beside_float64, (precision, g)
        assert g["late"] == 0 and g["builds"] >= 1, (precision, g)


def test_the_reference_type_follows_the_box_against_the_skin():
    from engine.loops.cuda_memory import xref_dtype, xref_margin
    from engine.setup.precision import XREF_MARGIN_SHARE, float32_reference_fits, float32_reference_skin

    skin = 1e-3
    # the largest box whose float32 rounding takes at most XREF_MARGIN_SHARE of L_v / 2
    edge = XREF_MARGIN_SHARE * 0.5 * skin / (math.sqrt(3.0) * 2.0 ** -24)
    assert xref_dtype(np.float64, [0.99 * edge], [skin]) == np.float32
    assert xref_dtype(np.float64, [0.99 * edge, 1.01 * edge], [skin, skin]) == np.float64   # every scene must fit
    assert xref_dtype(np.float32, [1e9], [skin]) == np.float32
    # the skin floor of the large-scene rule (engine.setup.params) is the thinnest skin that fits
    for box in (0.5, 2.0, 37.0):
        thinnest = float32_reference_skin(box)
        assert float32_reference_fits(box, thinnest) and not float32_reference_fits(box, thinnest * (1 - 1e-6))
    assert xref_margin(1.0, np.float64, np.float64) == xref_margin(1.0, np.float32, np.float32) == 0.0
    # the bound against float32 rounding of coordinates across [0, box)
    rng = np.random.default_rng(1)
    for box in (1e-3, 1.0, 37.5):
        x = rng.uniform(0.0, box, (3, 100000))
        err = np.sqrt(((x - x.astype(np.float32).astype(np.float64)) ** 2).sum(axis=0)).max()
        assert err <= xref_margin(box, np.float32, np.float64), (box, err)
