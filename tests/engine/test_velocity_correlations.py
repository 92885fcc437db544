"""engine/analysis/velocity_correlations.py: neighbour velocity correlations against exact cases."""

import math

import numpy as np
import pytest

from engine.analysis.velocity_correlations import neighbour_velocity_correlation


def test_independent_velocities_show_no_correlation():
    rng = np.random.default_rng(3)
    n, box, r_cut = 20_000, 1.0, 0.03
    out = neighbour_velocity_correlation(rng.random((n, 3)), rng.normal(size=(n, 3)), box, r_cut)
    # per pair v_i.v_j/<v^2> has standard deviation 1/sqrt(3), (g.r)^2/(2<v^2>/3) - 1 has sqrt(2): 4 SE bounds
    assert out["pairs"] > 5000
    assert abs(out["c_v"]) < 4 * (1 / math.sqrt(3)) / math.sqrt(out["pairs"]), out
    assert abs(out["g_n_ratio"]) < 4 * math.sqrt(2) / math.sqrt(out["approaching"]), out


def test_partners_with_equal_or_opposite_velocities():
    # 2000 tight pairs (0.004 apart, straddling the periodic boundary for some), pairs far from each other
    rng = np.random.default_rng(5)
    m, box, r_cut = 2000, 1.0, 0.01
    g = int(math.ceil(m ** (1 / 3)))
    centres = (np.stack(np.meshgrid(*[np.arange(g)] * 3, indexing="ij"), -1).reshape(-1, 3)[:m] + 0.5) / g - 0.5 / g
    d = rng.normal(size=(m, 3))
    d *= 0.002 / np.linalg.norm(d, axis=1)[:, None]
    pos = np.concatenate([centres - d, centres + d])      # spacing 1/13 of the box >> r_cut: only partners pair up
    u = rng.normal(size=(m, 3))
    u -= u.mean(0)
    same = neighbour_velocity_correlation(pos, np.concatenate([u, u]), box, r_cut)
    assert same["pairs"] == m and same["c_v"] == pytest.approx(1.0, abs=1e-12)
    assert same["approaching"] == 0 and math.isnan(same["g_n_ratio"])   # equal velocities never approach
    opposite = neighbour_velocity_correlation(pos, np.concatenate([u, -u]), box, r_cut)
    assert opposite["c_v"] == pytest.approx(-1.0, abs=1e-12)
    # g = -2u: <(g.r)^2> = 4 <(u.r)^2> = (4/3) <|u|^2> for isotropic r independent of u: ratio (4/3)/(2/3) - 1 = 1
    assert opposite["g_n_ratio"] == pytest.approx(1.0, abs=4 * math.sqrt(2) * 2 / math.sqrt(opposite["approaching"]))
    # the minimum image: shift everything by half a box, the pairs across the boundary still count
    shifted = neighbour_velocity_correlation(pos + 0.5, np.concatenate([u, u]), box, r_cut)
    assert shifted["pairs"] == m


def test_r_cut_beyond_half_the_box_is_refused():
    with pytest.raises(ValueError, match="r_cut"):
        neighbour_velocity_correlation(np.zeros((2, 3)), np.ones((2, 3)), 1.0, 0.6)


def test_file_correlations_read_every_snapshot_frame(tmp_path):
    from engine.output.h5md import read_frames
    from engine.driver.simulate import run
    from engine.setup.spec import SimulationSpec
    from engine.analysis.velocity_correlations import file_correlations

    spec = SimulationSpec(n_particles=256, volume_fraction=0.05, t_end=2e-4, thermalization=0, snapshots=3,
                          backend="cpu")
    run(spec, tmp_path / "out.h5")
    frames = list(read_frames(tmp_path / "out.h5"))
    r_cut = 0.2 * frames[0]["box"]
    got = file_correlations(tmp_path / "out.h5", r_cut)
    assert len(frames) >= 3 and got["time"].tolist() == [f["time"] for f in frames]
    for j, fr in enumerate(frames):
        one = neighbour_velocity_correlation(fr["position"], fr["velocity"], fr["box"], r_cut)
        assert got["c_v"][j] == one["c_v"] and got["pairs"][j] == one["pairs"]
