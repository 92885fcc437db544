"""The simulation process's progress messages (jobs/runner.py ``_hooks``): at most one per PROGRESS_SEND_S per job,
but a job's first and last report and every phase change always go to the worker."""

from __future__ import annotations

from types import SimpleNamespace

from engine.output.writers.progress import Progress
from jobs import runner


class Pipe:
    def __init__(self):
        self.sent = []

    def send(self, msg):
        self.sent.append(msg)


def _p(phase: str, fraction: float) -> Progress:
    return Progress(phase=phase, fraction=fraction, step=0, time=0.0, eta_s=1.0, cundall=1.0, loop_s=0.0)


def test_progress_is_throttled_but_keeps_first_last_and_phase_changes(monkeypatch):
    monkeypatch.setattr(runner, "PROGRESS_SEND_S", 3600.0)   # nothing goes out for the time alone
    conn = Pipe()
    specs = {0: SimpleNamespace(seed=1), 1: SimpleNamespace(seed=2)}
    progress, _ = runner._hooks(specs, conn, cancel_flags=[0, 0], parent_pid=0)
    reports = [("thermalization", f / 100) for f in range(10)] + [("cooling", f / 100) for f in range(10, 100)]
    for phase, f in reports:
        progress(0, _p(phase, f))
        progress(1, _p(phase, f))
    progress(0, _p("cooling", 1.0))
    sent0 = [(m[2]["phase"], m[2]["fraction"]) for m in conn.sent if m[1] == 0]
    sent1 = [(m[2]["phase"], m[2]["fraction"]) for m in conn.sent if m[1] == 1]
    assert sent0 == [("thermalization", 0.0), ("cooling", 0.10), ("cooling", 1.0)]
    assert sent1 == [("thermalization", 0.0), ("cooling", 0.10)]      # each job throttled on its own


def test_progress_goes_out_again_after_the_interval(monkeypatch):
    monkeypatch.setattr(runner, "PROGRESS_SEND_S", 0.0)
    conn = Pipe()
    progress, _ = runner._hooks({0: SimpleNamespace(seed=1)}, conn, cancel_flags=[0], parent_pid=0)
    for f in range(5):
        progress(0, _p("cooling", f / 10))
    assert len(conn.sent) == 5


def test_a_packs_progress_goes_out_as_one_message_for_all_its_jobs(monkeypatch):
    """A pack of 256 jobs reporting at each of 200 records: one ``progress_many`` message per interval with the
    latest report of each job (not one message per job: the pipe had filled and held the pack up), and whatever is
    gathered goes out before a job's final message."""
    clock = [0.0]
    monkeypatch.setattr(runner.time, "monotonic", lambda: clock[0])
    conn = Pipe()
    gathered = runner._PackProgress({k: SimpleNamespace(seed=k) for k in range(256)}, conn)
    for record in range(200):
        clock[0] = record * 0.01                   # a record every 10 ms of wall time
        for k in range(256):
            gathered.report(k, _p("cooling", record / 200))
    assert {m[0] for m in conn.sent} == {"progress_many"}
    assert runner.PROGRESS_SEND_S == 0.05
    assert 30 <= len(conn.sent) <= 41              # 2 s of records, at most one message per PROGRESS_SEND_S
    assert sum(len(m[2]) for m in conn.sent) <= 41 * 256
    last_sent = conn.sent[-1][2]
    gathered.report(7, _p("cooling", 1.0))         # within the interval: kept
    assert conn.sent[-1][2] is last_sent
    gathered.flush()                               # on_result's flush, before job 7's "done"
    assert conn.sent[-1][0] == "progress_many" and conn.sent[-1][2][7]["fraction"] == 1.0
    assert gathered.latest == {}
