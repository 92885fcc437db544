"""The list methods of Skorych & Dosta (2022) on the CUDA backend under the Numba CUDA simulator (CI has no GPU).

- The multigrid build on the GPU gives the brute-force contact set for size ratios 1, 2, 5, 10.
- The three list modes (GPU list, CPU list sequential, CPU list pipelined) give the same trajectory to
  rounding (different neighbour order only changes the summation order of the forces).

The simulator must be switched on before numba.cuda is first imported, so the checks run in two children,
side by side (one per core of the CI machine).
"""

import json

import numpy as np
import pytest

from tests.cudasim import run_children

pytestmark = pytest.mark.heavy   # the CUDA simulator's list builds (one shared run): about a minute of CPU


def poly_system(n, ratio, phi, seed, speed=1.0):
    """n spheres, radii log-uniform in [a/ratio, a] (a = 0.1), placed without overlap (largest first)."""
    from engine.backends.base import SphereSystem

    rng = np.random.default_rng(seed)
    a = 0.1
    r = np.sort(a * ratio ** (-rng.uniform(0.0, 1.0, n)))[::-1]
    if ratio > 1:
        r[0], r[-1] = a, a / ratio  # both ends of the range present
    box = (4.0 / 3.0 * np.pi * np.sum(r ** 3) / phi) ** (1.0 / 3.0)
    pos = np.zeros((n, 3))
    for i in range(n):
        for _ in range(100000):
            x = rng.uniform(0.0, box, 3)
            d = pos[:i] - x
            d -= box * np.round(d / box)
            if i == 0 or np.all(np.linalg.norm(d, axis=1) > r[:i] + r[i]):
                pos[i] = x
                break
        else:
            raise RuntimeError("placement failed")
    perm = rng.permutation(n)
    pos, r = pos[perm], r[perm]
    m = 1000.0 * 4.0 / 3.0 * np.pi * r ** 3
    vel = rng.normal(size=(n, 3)) * speed
    vel -= (m[:, None] * vel).sum(0) / m.sum()
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return SphereSystem(box_length=box, position=pos, velocity=vel, angular_velocity=rng.normal(size=(n, 3)),
                        orientation=q, radius=r, mass=m, inertia=0.4 * m * r * r)


def brute_pairs(pos, r, box, skin):
    d = pos[:, None, :] - pos[None, :, :]
    d -= box * np.round(d / box)
    dist = np.linalg.norm(d, axis=2)
    hit = dist < r[:, None] + r[None, :] + skin
    np.fill_diagonal(hit, False)
    return {(int(i), int(j)) for i, j in zip(*np.nonzero(hit))}


def contact(skin, dt, **kw):
    from engine.backends.base import ContactParams

    base = dict(k_n=1.0e5, gamma_n_coef=2.0 * np.sqrt(1.0e5) * 0.2, k_t=1.0e5 * 2 / 7 * 0.5, friction=0.3,
                dt=dt, skin=skin, precision="float64", orientation=True, overlap_limit=0.3)
    base.update(kw)
    return ContactParams(**base)


def _child_sets_and_per_phase() -> None:
    """The contact sets and the list modes in the one-launch-per-phase loop (one of the two children)."""
    modes, _ = _modes(multistep=False)
    mixed, _ = _modes(multistep=False, precision="mixed")
    print("RESULT", json.dumps({"sets": _sets(), "modes": modes, "mixed": mixed}))


def _child_multistep_and_growth() -> None:
    """The list modes in the many-steps-per-launch loop and the list growth (the other child): the growth
    check's reference is the GPU-list run of the same scene in that loop (the default at 40 particles), so
    that run is not repeated."""
    modes, gpu_ref = _modes(multistep=True)
    print("RESULT", json.dumps({"modes": modes, "growth": _growth(gpu_ref)}))


def _sets() -> dict:
    from engine.backends.cuda import CudaEnsemble

    out = {}
    for ratio in (1, 2, 5, 10):
        sy = poly_system(120, ratio, 0.25, seed=ratio)
        skin = 0.2 * float(sy.radius.min())
        ens = CudaEnsemble([sy], [contact(skin, 1e-4)])
        nbr, row, ids = ens.nbr.copy_to_host(), ens.nn.copy_to_host(), ens.ids.copy_to_host()
        nn = np.diff(row)
        got = {(int(ids[i]), int(ids[nbr[row[i] + k]])) for i in range(ens.n) for k in range(nn[i])}
        want = brute_pairs(np.asarray(sy.position), np.asarray(sy.radius), sy.box_length, skin)
        dup = sum(int(nn[i]) for i in range(ens.n)) - len(got)
        out[str(ratio)] = {"levels": ens.levels[0].n_levels if ens.multigrid else 1, "pairs": len(want),
                           "missing": len(want - got), "extra": len(got - want), "duplicates": dup}
    return out


def _modes(multistep: bool, precision: str = "float64"):
    """The list modes of one time loop (multistep: all three; per-phase: GPU list and CPU list pipelined) on
    one scene; returns {loop: their comparison} and the GPU-list run's final positions. ``precision`` 'mixed':
    the CPU-built lists read float64 positions (engine/setup/precision.py)."""
    from engine.backends.cuda import CudaBackend

    modes = ("gpu", "cpu-sequential", "cpu-pipelined") if multistep else ("gpu", "cpu-pipelined")
    runs = {}
    for mode in modes:
        sy = poly_system(40, 3.0, 0.3, seed=7, speed=1.0)
        skin = 0.3 * float(sy.radius.min())
        m12 = 0.5 * float(sy.mass.min())
        dt = np.pi * np.sqrt(m12 / 1.0e5) / 50
        be = CudaBackend(sy, contact(skin, dt, list_mode=mode, precision=precision))
        assert be.e.multistep  # the default here: the growth check's GPU reference is the multistep run
        be.e.multistep = multistep
        be.advance(100)
        st = be.state()
        runs[mode] = {"pos": st["position"], "vel": st["velocity"], "builds": be.builds,
                      "summary": None if be.e.lists is None else be.e.lists.summary(),
                      "contacts": be.observe()["contacts"]}
    ref = runs["gpu"]
    box = sy.box_length
    res = {"builds": {m: r["builds"] for m, r in runs.items()},
           "contacts": {m: r["contacts"] for m, r in runs.items()}}
    for mode in modes[1:]:
        d = runs[mode]["pos"] - ref["pos"]
        d -= box * np.round(d / box)
        res[mode] = {"dx": float(np.abs(d).max() / box),
                     "dv": float(np.abs(runs[mode]["vel"] - ref["vel"]).max() / np.abs(ref["vel"]).max()),
                     "stages": runs[mode]["summary"]["stages"], "restarts": runs[mode]["summary"]["restarts"]}
    return {"multistep" if multistep else "per-phase": res}, ref["pos"]


def _growth(gpu_ref) -> dict:
    """A CPU-built list that overflows its stride mid-run: the list grows and the contact history (springs)
    must survive it, so the run equals the GPU-list run (gpu_ref: the final positions of the GPU-list run of
    the same scene, 100 steps in one call, from _modes)."""
    from engine.backends.cuda import CudaBackend

    sy = poly_system(40, 3.0, 0.3, seed=7, speed=1.0)
    skin = 0.3 * float(sy.radius.min())
    dt = np.pi * np.sqrt(0.5 * float(sy.mass.min()) / 1.0e5) / 50
    be = CudaBackend(sy, contact(skin, dt, list_mode="cpu-sequential"))
    stride0 = be.e.lists._host["nbr"].shape[0]
    springs = []
    lists = be.e.lists
    real = lists.builder.build
    calls = []

    def build(pos, nbr, nn, x_ref=None):
        need = real(pos, nbr, nn, x_ref)
        calls.append(need)
        if len(calls) == 2:  # the second CPU build claims an overflow: the list must grow
            h, k = be.e.hist.copy_to_host(), be.e.nn.copy_to_host()
            # the slots in use: nn[i] .. nn[i + 1] - 1 (engine/loops/cuda_kernels.py, the list's layout)
            live = np.concatenate([np.arange(a, b) for a, b in zip(k[:-1], k[1:])]).astype(np.int64)
            springs.append(int((h[0, live] != 0).sum()))
            return nbr.shape[1] + 1
        return need

    lists.builder.build = build
    be.advance(100)
    d = be.state()["position"] - gpu_ref
    d -= sy.box_length * np.round(d / sy.box_length)
    return {"dx": float(np.abs(d).max() / sy.box_length), "stride": [stride0, be.e.lists._host["nbr"].shape[0]],
            "springs_at_growth": springs}


@pytest.fixture(scope="module")
def results():
    """The two children of this module, run side by side: contact sets + per-phase list modes; multistep list
    modes + list growth."""
    parts = ("_child_sets_and_per_phase", "_child_multistep_and_growth")
    code = ("from tests.cudasim import fast_block_polling; fast_block_polling(); "
            "from tests.engine.test_cuda_lists_simulator import {0}; {0}()")
    res = run_children({p: ["-c", code.format(p)] for p in parts}, timeout=1800)
    out = {}
    for part, (rc, stdout, stderr) in res.items():
        assert rc == 0, (part, stdout[-3000:] + stderr[-3000:])
        line = [x for x in stdout.splitlines() if x.startswith("RESULT ")][-1]
        out[part] = json.loads(line[7:])
    return out


def test_multigrid_gpu_contact_set_equals_brute_force(results):
    res = results["_child_sets_and_per_phase"]["sets"]
    print(res)
    for ratio, r in res.items():
        assert r["pairs"] > 0
        assert r["missing"] == 0 and r["extra"] == 0 and r["duplicates"] == 0, (ratio, r)
    assert res["1"]["levels"] == 1 and res["10"]["levels"] >= 3


def test_three_list_modes_same_trajectory(results):
    res = {**results["_child_multistep_and_growth"]["modes"], **results["_child_sets_and_per_phase"]["modes"]}
    assert set(res) == {"multistep", "per-phase"}
    print(res)
    for loop, r in res.items():
        assert min(r["builds"].values()) >= 3, (loop, r)  # the lists were rebuilt several times
        assert min(r["contacts"].values()) > 0, (loop, r)  # with contacts (forces and springs) at the end
        for mode in [m for m in ("cpu-sequential", "cpu-pipelined") if m in r]:
            # same physics and lists; only the order of the force sums differs: rounding, not O(dt)
            assert r[mode]["dx"] < 1e-11 and r[mode]["dv"] < 1e-8, (loop, mode, r[mode])
        assert r["cpu-pipelined"]["stages"] >= 3, (loop, r)


def test_list_modes_agree_in_mixed_precision(results):
    """'mixed' keeps float64 positions: the CPU-built list reads them from float64 host buffers; the modes differ
    only in the order of the float32 force sums (6e-8 per sum), through 100 steps with contacts."""
    r = results["_child_sets_and_per_phase"]["mixed"]["per-phase"]
    print(r)
    assert min(r["builds"].values()) >= 3 and min(r["contacts"].values()) > 0, r
    assert r["cpu-pipelined"]["stages"] >= 3, r
    assert r["cpu-pipelined"]["dx"] < 1e-7 and r["cpu-pipelined"]["dv"] < 1e-4, r


def test_cpu_list_growth_keeps_the_contact_history(results):
    res = results["_child_multistep_and_growth"]["growth"]
    print(res)
    assert res["stride"][1] > res["stride"][0]          # the list did grow
    assert res["springs_at_growth"] and res["springs_at_growth"][0] > 0  # with springs to carry over
    assert res["dx"] < 1e-11, res                       # rounding only: no spring was lost

