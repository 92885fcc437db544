"""Smoke test of bench/e2e.py: the time-to-result bench runs whole jobs through the public path and
its breakdown accounts for the wall time."""

from __future__ import annotations

import json

import pytest

from bench import e2e


def test_e2e_bench_quick_cases(tmp_path):
    assert e2e.main(["--quick", "--same-process", "--cases", "quickstart", "cpu-16x512", "batch-256x4096-2k",
                     "--out", str(tmp_path)]) == 0
    rows = {r["case"]: r for r in json.loads((tmp_path / "e2e.json").read_text())}
    assert set(rows) == {"quickstart", "cpu-16x512", "batch-256x4096-2k"}
    for r in rows.values():
        t = r["timings"]
        assert r["wall_s"] > 0 and 0 < r["loop_s"] <= r["wall_s"]
        assert r["e2e_cundall"] == pytest.approx(r["particles"] * r["steps"] / r["wall_s"])
        # the named phases plus "other" are the wall time, and nothing is negative but rounding
        assert sum(t.values()) == pytest.approx(r["wall_s"], rel=1e-9) and min(t.values()) > -0.05
    assert rows["batch-256x4096-2k"]["scenes"] == 4 and rows["cpu-16x512"]["ratio_to_one_scene"] > 0
    assert "| quickstart |" in (tmp_path / "e2e.md").read_text()
