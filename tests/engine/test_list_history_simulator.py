"""The CUDA list's history in packed rows (engine/loops/cuda_kernels.py, the list's layout), under the CUDA simulator:
nn (N + 1) holds the rows' first slots with the total in nn[N], the neighbour indices and the history
hold N + HIST_MARGIN slots until a build hands out more and then 5/4 of them plus the margin, and every fresh slot's
previous overlap is the pair's gap R_i + R_j - |r_ij| (negative: apart)."""

from __future__ import annotations

from tests.cudasim import run_children

SCRIPT = r'''
import json
import numpy as np
from tests.cudasim import fast_block_polling
fast_block_polling()
from tests.engine.test_cuda_lists_simulator import contact, poly_system
from engine.backends.cuda import CudaEnsemble
from engine.loops.cuda_memory import HIST_MARGIN, grown_history

out = {}
for name, phi, skin_r in (("dilute", 0.05, 0.4), ("dense", 0.3, 2.0)):
    sy = poly_system(64, 1.0, phi, seed=2)
    r = float(sy.radius[0])
    ens = CudaEnsemble([sy], [contact(skin_r * r, 1e-5)])
    nn, hist, nbr = ens.nn.copy_to_host(), ens.hist.copy_to_host(), ens.nbr.copy_to_host()
    pos = ens.pos.copy_to_host()
    n = ens.n
    rows = nn
    counts = np.diff(rows)
    total = int(counts.sum())
    assert nn.shape == (n + 1,) and rows[0] == 0 and (counts >= 0).all() and rows[n] == total, name
    want = n + HIST_MARGIN if total <= n + HIST_MARGIN else grown_history(total)
    assert hist.shape == (ens.hist_words, want) and nbr.shape == (want,), (name, hist.shape, nbr.shape, total)
    gaps = []
    for i in range(n):
        for kk in range(counts[i]):
            j = nbr[rows[i] + kk]
            d = pos[:, i] - pos[:, j]
            d -= sy.box_length * np.round(d / sy.box_length)
            gaps.append((hist[3, rows[i] + kk], 2 * r - np.linalg.norm(d), hist[0:3, rows[i] + kk].tolist()))
    g = np.array([(a, b) for a, b, _ in gaps])
    # fresh slots: the gap (to rounding: the host's minimum image rounds box multiples differently from min_image)
    assert np.allclose(g[:, 0], g[:, 1], rtol=0, atol=1e-12 * r), name
    assert all(x == [0.0, 0.0, 0.0] for _, _, x in gaps), name               # and no spring yet
    out[name] = dict(total=total, slots=int(hist.shape[1]), n=n, longest=int(counts.max()))
print("HIST-OK", json.dumps(out))
'''


def test_list_history_rows_are_packed_and_fresh_slots_hold_their_gap():
    import json

    rc, out, err = run_children({"run": ["-c", SCRIPT]}, timeout=900)["run"]
    assert rc == 0 and "HIST-OK" in out, out[-3000:] + err[-3000:]
    got = json.loads(out.split("HIST-OK", 1)[1])
    # the dense scene's list outgrew its first slots (rows longer than a strided list's first 8 slots among them)
    assert got["dense"]["longest"] > 8 and got["dense"]["total"] > got["dense"]["n"] + 1024
    assert got["dilute"]["slots"] == got["dilute"]["n"] + 1024
