"""Multigrid linked cells (Skorych & Dosta 2022, §2.2, Algorithm 1; engine/neighbours/multigrid.py) against brute
force."""

import math

import numpy as np
import pytest

from engine.neighbours.multigrid import MultigridBuilder, grid_levels, main_level

BOX = 1.0


def _brute(pos, radius, skin, box):
    """Boolean (N, N) all-pairs Verlet relation |r_ij| < R_i + R_j + L_v (minimum image), numpy float64."""
    d = pos[:, None, :] - pos[None, :, :]
    d -= box * np.round(d / box)
    r2 = (d**2).sum(-1)
    rc = radius[:, None] + radius[None, :] + skin
    out = r2 < rc * rc
    np.fill_diagonal(out, False)
    return out


def _listed(nbr, nn):
    n = nn.shape[0]
    out = np.zeros((n, n), bool)
    for i in range(n):
        row = nbr[i, :nn[i]]
        assert len(set(row.tolist())) == nn[i], f"duplicate neighbour in row {i}"
        out[i, row] = True
    return out


def _radii(kind, ratio, n, rng, r_max):
    r_min = r_max / ratio
    if kind == "two":
        r = np.where(rng.random(n) < 0.5, r_max, r_min)
    elif kind == "four":
        r = r_max * np.array([1.0, 0.6, 0.35, 1.0 / ratio])[rng.integers(0, 4, n)]
        r = np.minimum(r, r_max)
        r = np.maximum(r, r_min)
    else:  # continuous, log-uniform spread
        r = r_min * ratio ** rng.random(n)
    r[0], r[1] = r_max, r_min
    return r


def _scene(ratio, kind, n, seed, r_max=0.03, skin_frac=0.4):
    rng = np.random.default_rng(seed)
    radius = _radii(kind, ratio, n, rng, r_max)
    skin = skin_frac * radius.min()
    pos = rng.random((n, 3)) * BOX
    # periodic images: particles hugging the faces, edges and corners of the box
    pos[2] = [0.0, 0.0, 0.0]
    pos[3] = [BOX * (1 - 1e-12), BOX * (1 - 1e-12), BOX * (1 - 1e-12)]
    pos[4] = [0.5 * r_max, BOX - 0.5 * r_max, 0.3]
    pos[5] = [BOX - 0.2 * r_max, 0.1 * r_max, BOX - 0.4 * r_max]
    return pos, radius, skin


def _build(pos, radius, skin, stride=64):
    n = len(radius)
    levels = grid_levels(BOX, n, radius.min(), radius.max(), skin)
    b = MultigridBuilder(BOX, radius, levels)
    nbr = np.full((n, stride), -1, np.int32)
    nn = np.zeros(n, np.int32)
    need = b.build(pos, nbr, nn)
    while need > nbr.shape[1]:
        nbr = np.full((n, need), -1, np.int32)
        need = b.build(pos, nbr, nn)
    return levels, nbr, nn


def test_levels_follow_eqs_3_and_4():
    r_max, skin = 0.02, 0.001
    lv = grid_levels(BOX, 10_000, r_max / 10, r_max, skin)
    assert lv.n_levels == 4
    assert lv.cell[0] == 2 * r_max + skin
    assert np.all(lv.cell[1:] == lv.cell[:-1] / 2)
    assert np.allclose(lv.u_min, lv.cell / 4 - skin / 2, rtol=0, atol=1e-15)        # Eq. 4
    assert lv.u_max[0] == r_max and np.all(lv.u_max[1:] == lv.u_min[:-1])           # Eq. 3, bit-equal
    assert np.all(BOX / lv.nc >= lv.cell) and np.all(lv.nc**3 <= 8 * 10_000)
    assert lv.u_min[-1] < r_max / 10 <= lv.u_min[-2]
    # one size: one level, the single grid of edge >= 2 R + L_v
    assert grid_levels(BOX, 100, r_max, r_max, skin).n_levels == 1
    assert grid_levels(BOX, 100, r_max / 100, r_max, skin, max_levels=3).n_levels == 3
    # coarse grids with nc < 3, and the cap nc^3 <= max(8, 8N)
    small = grid_levels(BOX, 2, 0.01, 0.3, 0.0)
    assert small.nc[0] == 1 and small.nc[1] == 2          # floor(1/0.3) = 3, capped: 3^3 > max(8, 16)
    assert np.all(small.nc**3 <= 16)


def test_main_level_includes_band_edges():
    """The strict U_min < R < U_max of Skorych & Dosta (2022) would drop R = R_max and R = U_max^j; ours keeps both."""
    r_max, skin = 0.02, 0.001
    lv = grid_levels(BOX, 1000, r_max / 10, r_max, skin)
    edges = np.concatenate([[r_max, r_max / 10], lv.u_min[:-1], np.nextafter(lv.u_min[:-1], 1.0)])
    lev = main_level(edges, lv)
    assert lev.dtype == np.int32
    for r, l in zip(edges, lev):
        assert r <= lv.u_max[l]
        assert r > lv.u_min[l] or l == lv.n_levels - 1
    assert lev[0] == 0
    # R exactly U_min^j is secondary at j and main one level finer, where it equals U_max^(j+1)
    assert np.all(lev[2:2 + lv.n_levels - 1] == np.arange(1, lv.n_levels))


@pytest.mark.parametrize("ratio", [1, 2, 5, 10])
@pytest.mark.parametrize("kind", ["two", "four", "continuous"])
def test_contact_set_equals_brute_force(ratio, kind):
    n = 700
    pos, radius, skin = _scene(ratio, kind, n, seed=ratio * 7 + len(kind))
    levels, nbr, nn = _build(pos, radius, skin)
    if ratio >= 5:
        assert levels.n_levels >= 3
    want = _brute(pos, radius, skin, BOX)
    got = _listed(nbr, nn)
    assert np.array_equal(got, want)
    assert np.array_equal(got, got.T)                 # full list: j in row i iff i in row j
    assert np.array_equal(nn, want.sum(1))


def test_band_edge_radii_and_dense_contacts():
    """Radii exactly on every level boundary, packed so that many pairs are within the cutoff."""
    rng = np.random.default_rng(5)
    r_max, skin = 0.03, 0.0012
    lv = grid_levels(BOX, 800, r_max / 10, r_max, skin)
    choices = np.concatenate([[r_max, r_max / 10], lv.u_min[:-1], lv.u_min[:-1] * (1 + 1e-15)])
    radius = choices[rng.integers(0, len(choices), 800)]
    radius[0], radius[1] = r_max, r_max / 10
    pos = rng.random((800, 3)) * 0.35 * BOX          # crowd them: overlapping and touching pairs
    _, nbr, nn = _build(pos, radius, skin)
    want = _brute(pos, radius, skin, BOX)
    assert want.sum() > 1000
    assert np.array_equal(_listed(nbr, nn), want)


def test_coarse_grids_with_fewer_than_three_cells():
    """Large spheres in a small box: nc_0 = 1 or 2 (the 27 neighbour cells collapse); still exact."""
    for n, r_max in ((12, 0.3), (40, 0.17)):
        rng = np.random.default_rng(n)
        radius = np.where(rng.random(n) < 0.3, r_max, r_max / 8)
        radius[0], radius[1] = r_max, r_max / 8
        skin = 0.4 * r_max / 8
        lv = grid_levels(BOX, n, radius.min(), radius.max(), skin)
        assert lv.nc[0] < 3 and lv.n_levels >= 3
        pos = rng.random((n, 3)) * BOX
        _, nbr, nn = _build(pos, radius, skin)
        assert np.array_equal(_listed(nbr, nn), _brute(pos, radius, skin, BOX))


def test_transposed_gpu_layout_and_overflow():
    """The GPU list is [max_nb, N]; the builder fills its transpose, and reports overflow by the count."""
    pos, radius, skin = _scene(10, "continuous", 500, seed=3)
    n = len(radius)
    lv = grid_levels(BOX, n, radius.min(), radius.max(), skin)
    b = MultigridBuilder(BOX, radius, lv)
    ref_nbr = np.zeros((n, 128), np.int32)
    ref_nn = np.zeros(n, np.int32)
    need = b.build(pos, ref_nbr, ref_nn)
    assert 2 <= need <= 128
    small = np.full((need - 1, n), -7, np.int32)          # device layout, one slot too few
    nn = np.zeros(n, np.int32)
    x_ref = np.zeros((n, 3))
    assert b.build(pos, small.T, nn, x_ref) == need
    assert np.array_equal(nn, ref_nn) and np.array_equal(x_ref, pos)
    for i in range(n):
        k = min(nn[i], need - 1)
        assert np.array_equal(small[:k, i], ref_nbr[i, :k])
        assert np.all(small[k:, i] == -7)                  # nothing written beyond the stride
    big = np.zeros((need, n), np.int32)
    b.build(pos, big.T, nn)
    assert all(np.array_equal(big[:nn[i], i], ref_nbr[i, :nn[i]]) for i in range(n))


def test_candidates_shrink_with_multigrid():
    """The point of the multigrid: at size ratio 10 a small sphere tests far fewer pairs."""
    rng = np.random.default_rng(11)
    radius = np.where(rng.random(3000) < 0.05, 0.05, 0.005)      # 5 % large ones, ratio 10
    skin = 0.4 * 0.005
    pos = rng.random((3000, 3)) * BOX
    lv = grid_levels(BOX, len(radius), radius.min(), radius.max(), skin)
    one = grid_levels(BOX, len(radius), radius.max(), radius.max(), skin)
    multi = MultigridBuilder(BOX, radius, lv).candidates(pos)
    single = MultigridBuilder(BOX, radius, one).candidates(pos)
    small = radius < radius.max()
    # the single grid's candidates are the particles in 27 cells of edge >= 2 R_max + L_v
    assert multi[small].mean() < 0.2 * single[small].mean()


def test_cpu_backend_uses_multigrid_and_keeps_springs():
    """CPU backend on a polydisperse gas: multigrid lists hold every contact between rebuilds, and
    the same scene with a thin skin (many rebuilds) and a thick one (few) gives the same trajectory."""
    from engine.backends.base import ContactParams, SphereSystem
    from engine.shapes.sphere.cpu_backend import CpuBackend
    from engine.setup.params import gamma_n_from_restitution, k_t_paper
    from engine.setup.scene import place_species

    rng = np.random.default_rng(2)
    counts, radii = (24, 150), (0.01, 0.0025)
    phi = 0.25
    box = (sum(c * 4 / 3 * math.pi * r**3 for c, r in zip(counts, radii)) / phi) ** (1 / 3)
    pos, species = place_species(counts, radii, box, rng)
    n = len(pos)
    radius = np.asarray(radii)[species]
    mass = 2000.0 * 4 / 3 * math.pi * radius**3
    inertia = 0.4 * mass * radius**2
    t0 = 1e-5      # J: typical overlap sqrt(3 T0/k_n) = 4 % of the small radius at k_n below
    vel = rng.normal(size=(n, 3)) * np.sqrt(t0 / mass)[:, None]
    omega = rng.normal(size=(n, 3)) * np.sqrt(t0 / inertia)[:, None]
    k_n = 1e3
    m12 = mass.min() / 2
    dt = math.pi * math.sqrt(m12 / k_n) / 50
    runs = []
    for skin in (0.05, 1.0):
        system = SphereSystem(box, pos.copy(), vel.copy(), omega.copy(), np.tile([1.0, 0, 0, 0], (n, 1)),
                              radius, mass, inertia)
        params = ContactParams(k_n=k_n, gamma_n_coef=gamma_n_from_restitution(0.7, k_n, m12) / math.sqrt(m12),
                               k_t=k_t_paper(0.5, k_n), friction=None, dt=dt, skin=skin * radii[1],
                               overlap_limit=0.3)
        be = CpuBackend(system, params)
        assert be.mg is not None and be.levels.n_levels >= 2
        seen = 0
        for _ in range(8):
            be.advance(250)
            listed = _listed(be.nbr, be.nn)
            assert np.all(listed[_brute(be.pos, be.radius, 0.0, box)])
            seen += be.observe()["contacts"]
        runs.append((be.pos.copy(), be.omega.copy(), be.builds, seen))
    (p1, w1, b1, c1), (p2, w2, b2, c2) = runs
    assert b1 > 3 * b2 and c1 > 0
    # only the summation order differs (rounding); a lost spring would change spins at O(1)
    assert np.abs(w1 - w2).max() < 1e-8 * np.abs(w1).max()
    assert np.abs(p1 - p2).max() < 1e-10


def _rows_by_neighbour_cell(b: MultigridBuilder, pos) -> list:
    """Every particle's row as engine/neighbours/multigrid.py's search rule gives it when it takes its cells from
    engine.neighbours.cells.neighbour_cell, one k at a time (plain Python over the builder's bins)."""
    from engine.neighbours.cells import cell_coords, distance2, neighbour_cell, neighbour_cell_count

    rows = []
    for i in range(b.n):
        row, li = [], b.level[i]
        for l in range(li + 1):
            s0, l0, ncl = b.start_off[l], b.list_off[l], b.nc[l]
            span = 1 if l < li else 2
            cx, cy, cz = cell_coords(pos[i, 0], pos[i, 1], pos[i, 2], b.inv_cell[l], ncl)
            for k in range(neighbour_cell_count(ncl)):
                key = 2 * neighbour_cell(cx, cy, cz, k, ncl)
                for s in range(b.cell_start[s0 + key], b.cell_start[s0 + key + span]):
                    j = b.cell_list[l0 + s]
                    rc = b.radius[i] + b.radius[j] + b.skin
                    if j != i and distance2(*pos[i], *pos[j], b.box, b.inv_box, b.half) < rc * rc:
                        row.append(j)
        rows.append(row)
    return rows


@pytest.mark.parametrize("ratio, n, r_max", [(5, 700, 0.03), (8, 40, 0.3)])
def test_rows_come_in_neighbour_cell_order(ratio, n, r_max):
    """The search walks the neighbour cells as nested offset loops (no division per cell): every row holds the same
    neighbours in the same order as a walk by neighbour_cell, so the forces sum in the same order; on grids of
    fewer than three cells per side too (40 spheres, the large ones of 0.3 box)."""
    pos, radius, skin = _scene(ratio, "two", n, seed=ratio, r_max=r_max)
    levels = grid_levels(BOX, n, radius.min(), radius.max(), skin)
    assert levels.n_levels >= 2 and (min(levels.nc) < 3) == (r_max > 0.1)
    b = MultigridBuilder(BOX, radius, levels)
    nbr, nn = np.full((n, n), -1, np.int32), np.zeros(n, np.int32)
    b.build(pos, nbr, nn)
    want = _rows_by_neighbour_cell(b, pos)
    assert sum(len(r) for r in want) >= 20          # rows with entries to compare
    for i in range(n):
        assert nbr[i, :nn[i]].tolist() == want[i], i
