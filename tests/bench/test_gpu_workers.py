"""The harness of bench/gpu_workers.py on a CPU machine: one queue, two workers that see no GPU, the jobs run by
the instant engine (bench/load_service.py), so what is checked is the harness, not the physics: every job accounted
for once, each worker's share read from its log, the speed-up printed."""

from __future__ import annotations

import json

from bench import gpu_workers


def test_two_workers_drain_one_sweep_and_every_job_is_accounted_for_once(tmp_path, monkeypatch):
    monkeypatch.setenv("DEMQ_ENGINE_RUN", "bench.load_service:instant_run")
    monkeypatch.setenv("DEMQ_POLL_SECONDS", "0.05")
    assert gpu_workers.main(["--devices", "", "", "--jobs", "12", "--n", "64", "--steps", "10", "--idle-s", "0",
                             "--out", str(tmp_path)]) == 0
    got = json.loads((tmp_path / "gpu_workers.json").read_text())
    one, both = got["runs"]
    assert one["workers"] == 1 and both["workers"] == 2
    for r in (one, both):
        assert r["jobs"] == 12 and not r["problems"] and r["backends"] == ["instant"]
        assert sum(r["jobs_per_worker"].values()) == 12
    assert min(both["jobs_per_worker"].values()) > 0
    assert got["base"]["n_particles"] == 64 and round(got["base"]["t_end"] / got["base"]["dt"]) == 10


def test_only_a_done_line_counts_a_job_done(tmp_path):
    """The accounting reads a worker's "job <id>: done" lines only (a failed job is not counted)."""
    log = tmp_path / "w.log"
    log.write_text("job aaa: done\njob bbb: failed\n")
    assert gpu_workers.DONE.findall(log.read_text()) == ["aaa"]
