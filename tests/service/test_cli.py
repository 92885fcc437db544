"""The command line's handling of bad input, in process (``main(argv)``): one clear line per problem on
stderr, exit status 2, nothing written, no traceback; and its progress lines off a terminal.

The runs that reach the engine (the result and its sidecar) are in tests/service/test_durability.py
(``demq submit --local --wait -o``) and tests/engine/test_progress.py (``demq run``).
"""

from __future__ import annotations

import io

import pytest

from engine.driver.progress import ProgressLines, progress_for
from service.cli import main


def _run(argv, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    out, err = capsys.readouterr()
    return exit_.value.code, out, err


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.mark.parametrize("command", [["run"], ["submit", "--local"]])
def test_missing_spec_file_is_one_line_and_exit_2(command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = _run([*command, str(tmp_path / "nonexistent.json")], capsys)
    assert code == 2
    assert "nonexistent.json' does not exist" in _one_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == []       # no result, no queue


@pytest.mark.parametrize("command", [["run"], ["submit", "--local"]])
@pytest.mark.parametrize("text, words", [("{not json", "is not valid JSON: Expecting property name"),
                                         ("[1, 2]", "must hold a JSON object of spec keys, not a JSON list"),
                                         ("", "is not valid JSON")])
def test_malformed_spec_file_is_one_line_and_exit_2(command, text, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.json"
    spec.write_text(text)
    code, _, err = _run([*command, str(spec)], capsys)
    assert code == 2 and words in _one_line(err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.json"]


@pytest.mark.parametrize("command", [["run"], ["submit", "--local"]])
@pytest.mark.parametrize("sets, words", [
    (["n_particles=abc"], "n_particles = 'abc': Input should be a valid integer"),
    (["e_n=3"], "e_n = 3.0 is outside the allowed range (0, 1]"),
    (["colour=red"], "colour = 'red': 'colour' is not a spec key"),
    (["backend=gpu"], "backend = 'gpu': Input should be 'auto', 'cpu' or 'cuda'"),
    (["n_particles"], "--set 'n_particles' is not KEY=VALUE"),
])
def test_every_message_names_the_field_and_the_value(command, sets, words, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = _run([*command, *(a for s in sets for a in ("--set", s))], capsys)
    assert code == 2 and words in _one_line(err), err
    assert list(tmp_path.iterdir()) == []


def test_run_beyond_the_cost_limit_is_refused_up_front_with_its_estimate(tmp_path, capsys):
    out = tmp_path / "big.h5"
    code, _, err = _run(["run", "--set", "n_particles=1e8", "--set", "t_end=1e9", "-o", str(out)], capsys)
    assert code == 2 and "Traceback" not in err
    assert "particle-steps (100000000 particles x" in err and "DEMQ_MAX_PARTICLE_STEPS = 1e+12" in err
    assert "--allow-large" in err
    assert list(tmp_path.iterdir()) == []                           # no file for a refused job


def test_allow_large_lifts_the_refusal(tmp_path, capsys):
    """With --allow-large the cost refusal is gone; the run then stops at the next check (its output folder
    does not exist), so no simulation starts in this test."""
    out = tmp_path / "no-such-folder" / "big.h5"
    code, _, err = _run(["run", "--allow-large", "--set", "n_particles=1e8", "--set", "t_end=1e9", "-o", str(out)],
                        capsys)
    assert code == 2 and "refused" not in err
    assert "no-such-folder' does not exist" in _one_line(err)


def test_submit_output_needs_wait(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = _run(["submit", "--local", "-o", "r.h5"], capsys)
    assert code == 2 and "needs --wait" in _one_line(err)


def test_submit_local_refuses_a_job_beyond_the_limit_before_queueing(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = _run(["submit", "--local", "--wait", "-o", "r.h5", "--set", "n_particles=1e8",
                           "--set", "t_end=1e9"], capsys)
    assert code == 2 and out == "" and "DEMQ_MAX_PARTICLE_STEPS" in err
    assert not (tmp_path / "r.h5").exists()


def test_bench_is_not_a_subcommand(capsys):
    code, _, err = _run(["bench"], capsys)
    assert code == 2 and "invalid choice: 'bench'" in err


def test_progress_off_a_terminal_is_plain_lines_every_10_percent():
    stream = io.StringIO()                                         # isatty() is False
    progress = progress_for(4096, desc="job 1234abcd ", stream=stream)
    assert isinstance(progress, ProgressLines)
    for k in range(1, 101):
        progress.update(k / 100, "cooling", eta_s=100 - k, cundall=8.192e6)
    progress.close()
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue()
    assert [line.split("%")[0].split(": ")[1].strip() for line in lines] == [
        "10.0", "20.0", "30.0", "40.0", "50.0", "60.0", "70.0", "80.0", "90.0", "100.0"]
    assert lines[0] == "job 1234abcd:  10.0%  N=4096  2e+03 steps/s  Cundall 8.19e+06  ETA 01:30  cooling"


def test_progress_lines_also_come_every_few_seconds_of_a_slow_run():
    stream = io.StringIO()
    progress = ProgressLines(64, stream=stream, every_s=0.0)       # every update is "late"
    progress.update(0.01, "thermalization")
    progress.update(0.02, "thermalization")
    assert len(stream.getvalue().splitlines()) == 2
