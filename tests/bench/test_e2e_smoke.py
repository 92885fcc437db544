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


def test_every_off_switch_names_an_engine_setting_that_is_on_by_default(monkeypatch):
    """--off NAME sets a module-level engine setting: each one exists and is not already its off value, and
    switch_off sets it (an engine rename would otherwise make an A/B compare a run with itself)."""
    import importlib

    for name, (module, setting, off_value) in e2e.SWITCHES.items():
        mod = importlib.import_module(module)
        assert hasattr(mod, setting), (name, module, setting)
        assert getattr(mod, setting) != off_value, (name, getattr(mod, setting))
        monkeypatch.setattr(mod, setting, getattr(mod, setting))   # restored after the test
        e2e.switch_off([name])
        assert getattr(mod, setting) == off_value, name
    with pytest.raises(ValueError, match="unknown switch"):
        e2e.switch_off(["no-such-switch"])


def test_a_fresh_process_case_reports_the_process_seconds():
    """The fresh-process path also times the whole process (interpreter start to exit), which holds the call."""
    row = e2e.fresh_process("quickstart", quick=True)
    assert 0 < row["wall_s"] < row["process_s"]
    assert row["runner_imported"] is True       # the default: the runner is imported before the clock


def test_public_calls_import_the_runner_inside_the_call():
    """--public: engine.run is called with nothing of engine.driver imported before the clock, so that the call's
    wall time holds the runner's import; a case the flag cannot time that way is refused."""
    row = e2e.fresh_process("quickstart", quick=True, public=True)
    assert row["runner_imported"] is False and 0 < row["wall_s"] < row["process_s"]
    with pytest.raises(RuntimeError, match="--public"):
        e2e.fresh_process("quickstart", quick=True, trace=True, public=True)


def test_the_trace_times_every_step_it_names_in_a_fresh_process():
    """--trace: every traced step exists (an engine rename would otherwise trace nothing), and a fresh process's
    CPU job reports its set-up, build and file steps within the call, in order."""
    import importlib

    for module, cls, attr in e2e.TRACED:
        owner = importlib.import_module(module)
        assert hasattr(getattr(owner, cls) if cls else owner, attr), (module, cls, attr)
    row = e2e.fresh_process("quickstart", quick=True, trace=True)
    steps = {step: (a, b) for a, b, _, step in row["trace"]}
    assert {"SceneRun.__init__", "simulate._build", "H5MDWriter.finish_async"} <= set(steps), steps
    assert 0 <= steps["SceneRun.__init__"][0] <= steps["simulate._build"][0] <= steps["H5MDWriter.finish_async"][0]
    assert steps["H5MDWriter.finish_async"][1] <= row["wall_s"] + 0.01
