"""Smoke test of bench/multigrid_cost.py on a tiny scene (the measured table is in docs/performance.md)."""

import json

from bench import multigrid_cost


def test_multigrid_cost_tiny(tmp_path, capsys):
    multigrid_cost.main(["--n", "3000", "--ratios", "1", "10", "--reps", "1", "--threads", "1",
                         "--out", str(tmp_path)])
    data = json.loads((tmp_path / "multigrid_cost.json").read_text())
    one, ten = data["rows"]
    assert one["n_levels"] == 1 and ten["n_levels"] >= 3
    # same pairs on both grids is asserted inside measure(); the multigrid must test fewer candidates
    assert one["candidates_multi"] == one["candidates_single"]
    assert ten["candidates_multi_small"] < 0.1 * ten["candidates_single_small"]
    assert "| 10 |" in capsys.readouterr().out
