"""engine/analysis/pairs.py: the cell list finds exactly the pairs that a test of every pair finds."""

import numpy as np
import pytest

from engine.analysis.pairs import periodic_pairs


def all_pairs(x, box, r_cut):
    """Every pair tested, minimum image: the reference set, sorted like periodic_pairs'."""
    x = np.mod(np.asarray(x, dtype=float), box)
    i, j = np.triu_indices(len(x), k=1)
    r = x[j] - x[i]
    r -= box * np.round(r / box)
    near = np.einsum("ij,ij->i", r, r) <= r_cut**2
    return np.stack([i[near], j[near]], axis=1).astype(np.int64)


@pytest.mark.parametrize("n,box,r_cut", [
    (0, 1.0, 0.1), (1, 1.0, 0.1), (400, 1.0, 0.49),      # no points, one point, fewer than 3 cells (all pairs)
    (400, 1.0, 0.3), (3000, 5.0, 0.5), (2000, 10.0, 1.0),  # 3, 10 and 10 (capped at N^1/3 = 12) cells per edge
    (2000, 2.0, 0.0),
])
def test_the_same_pairs_as_testing_every_pair(n, box, r_cut):
    rng = np.random.default_rng(n)
    x = rng.uniform(-box, 2.0 * box, (n, 3))            # positions outside the box are wrapped
    got = periodic_pairs(x, box, r_cut)
    assert got.dtype == np.int64 and got.shape[1] == 2
    assert np.array_equal(got, all_pairs(x, box, r_cut))


def test_pairs_at_exactly_the_cut_and_across_the_boundary():
    # a simple cubic lattice of spacing 1 in a box of 6: every site has 6 neighbours at exactly r_cut = 1,
    # half of them through the periodic boundary for the sites on a face
    g = np.arange(6.0)
    x = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pairs = periodic_pairs(x, 6.0, 1.0)
    assert len(pairs) == 216 * 3
    assert np.array_equal(np.bincount(pairs.ravel(), minlength=216), np.full(216, 6))
    assert np.array_equal(pairs, all_pairs(x, 6.0, 1.0))
    assert len(periodic_pairs(x, 6.0, 0.999)) == 0
    # shifting every point by any vector changes no distance
    assert np.array_equal(periodic_pairs(x + np.array([0.37, -2.9, 6.5]), 6.0, 1.0), pairs)


def test_r_cut_outside_zero_to_half_the_box_is_refused():
    with pytest.raises(ValueError, match="r_cut"):
        periodic_pairs(np.zeros((2, 3)), 1.0, 0.5)
    with pytest.raises(ValueError, match="r_cut"):
        periodic_pairs(np.zeros((2, 3)), 1.0, -0.1)
    with pytest.raises(ValueError, match="shape"):
        periodic_pairs(np.zeros((2, 2)), 1.0, 0.1)


@pytest.mark.heavy
def test_the_same_pairs_as_scipy_ckdtree():
    """Against scipy's periodic k-d tree, which engine/analysis/velocity_correlations.py used before (the reference
    extra)."""
    spatial = pytest.importorskip("scipy.spatial", reason="scipy (pip install '.[reference]')")
    rng = np.random.default_rng(11)
    for n, box, r_cut in ((20_000, 20.0, 1.0), (5000, 1.0, 0.03), (300, 1.0, 0.45)):
        x = rng.uniform(0.0, box, (n, 3))
        ref = spatial.cKDTree(x, boxsize=box).query_pairs(r_cut, output_type="ndarray")
        ref = np.sort(ref, axis=1)
        ref = ref[np.lexsort((ref[:, 1], ref[:, 0]))]
        assert np.array_equal(periodic_pairs(x, box, r_cut), ref)
