"""A newcomer's cases of the command line, in process (``main(argv)``): every error is one line on stderr
naming the problem and the fix, no traceback, exit status 2 for a usage error (a bad key, a backend this machine
cannot run, a missing file or extra) and 1 for work that failed (no server or database answers).

Bad spec files and values are in tests/service/test_cli.py (whose helpers these tests use). The real
`demq validate sonine --quick` takes 30-40 s on 2 cores (tests/validation/test_sonine_reduced.py runs it, heavy),
so its no-matplotlib path is run here on a smaller call of the same function.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import socket
import stat

import httpx
import numpy as np
import pytest

import engine.backends.base
from engine.validation import sonine
from service.cli import build_parser
from tests.extras import NO_POSTGRES, hide_matplotlib, hide_psycopg
from tests.jobs.conftest import postgres_driver
from tests.service.test_cli import _one_line, _run


@pytest.fixture
def refused_url() -> str:
    """A local URL where nothing listens (a port the kernel just handed out and took back)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"http://127.0.0.1:{port}"


@pytest.fixture
def no_gpu(monkeypatch):
    """This machine, seen without a CUDA GPU (and without the CUDA simulator) whatever it has."""
    monkeypatch.delenv("NUMBA_ENABLE_CUDASIM", raising=False)
    monkeypatch.setattr(engine.backends.base, "cuda_available", lambda: False)


@pytest.mark.parametrize("command", [["status"], ["status", "0123abcd"], ["submit", "SPEC"],
                                     ["fetch", "0123abcd", "-o", "OUT"]])
def test_no_server_is_one_line_naming_the_url_and_the_fix(command, refused_url, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"n_particles": 64}))
    argv = [str(spec) if a == "SPEC" else str(tmp_path / "r.h5") if a == "OUT" else a for a in command]
    code, out, err = _run([*argv, "--url", refused_url], capsys)
    assert code == 1 and out == ""
    assert _one_line(err) == (f"demq {command[0]}: cannot reach the server at {refused_url} (connection refused); "
                              f"start it with `demq serve` or set --url/DEMQ_URL")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.json"]       # no result, no .part


@pytest.mark.parametrize("status, detail, line", [
    (404, "no job with id '0123abcd'", "demq status: HTTP 404: no job with id '0123abcd'"),
    (401, "missing or wrong bearer token",
     "demq status: HTTP 401: missing or wrong bearer token; pass the server's token with --token/DEMQ_TOKEN"),
])
def test_an_error_answer_of_the_service_is_one_line(status, detail, line, capsys, monkeypatch):
    transport = httpx.MockTransport(lambda request: httpx.Response(status, json={"detail": detail}))
    monkeypatch.setattr(httpx, "Client", functools.partial(httpx.Client, transport=transport))
    code, _, err = _run(["status", "0123abcd", "--url", "http://demq.example:8000"], capsys)
    assert code == 1 and _one_line(err) == line


def test_a_url_that_is_not_http_is_a_usage_error(capsys):
    code, _, err = _run(["status", "--url", "localhost:8000"], capsys)
    assert code == 2
    assert "'localhost:8000' is not an http(s) URL" in _one_line(err) and "--url/DEMQ_URL" in err


@pytest.mark.parametrize("argv", [["run", "--set", "backend=cuda"], ["run", "--backend", "cuda"], ["run", "SPEC"],
                                  ["submit", "--local", "--wait", "--set", "backend=cuda"],
                                  ["validate", "sonine", "--quick", "--backend", "cuda"],
                                  ["warm", "--backend", "cuda"]])
def test_cuda_without_a_gpu_is_refused_up_front(argv, no_gpu, tmp_path, capsys, monkeypatch):
    """Refused before any run (within the test's time: no kernel is compiled, no file or queue made)."""
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"backend": "cuda", "n_particles": 64}))
    code, out, err = _run([str(spec) if a == "SPEC" else a for a in argv], capsys)
    assert code == 2 and out == ""
    assert _one_line(err).startswith(f"demq {argv[0]}: backend = 'cuda' but no CUDA GPU is available here; ")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spec.json"]


@pytest.mark.parametrize("where", ["--set", "file"])
@pytest.mark.parametrize("command", [["run"], ["submit", "--local"]])
def test_a_misspelt_key_gets_the_spec_key_it_is_closest_to(where, command, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"n_partcles": 5}))
    code, _, err = _run([*command, *(["--set", "n_partcles=5"] if where == "--set" else [str(spec)])], capsys)
    assert code == 2
    assert _one_line(err).endswith("invalid spec: n_partcles = 5: 'n_partcles' is not a spec key; "
                                   "did you mean 'n_particles'?")


def test_a_misspelt_key_of_a_species_gets_the_species_key(tmp_path, capsys):
    species = [{"radius_ratio": 1.0, "number_fraction": 0.5}, {"radius_ratio": 2.0, "number_fraction": 0.5,
                                                              "radius_ratoi": 2.0}]
    code, _, err = _run(["run", "--set", f"species={json.dumps(species)}", "-o", str(tmp_path / "r.h5")], capsys)
    assert code == 2
    assert "species.1.radius_ratoi = 2.0: 'radius_ratoi' is not a spec key; did you mean 'radius_ratio'?" in err


def test_an_unknown_key_far_from_every_spec_key_gets_no_suggestion(capsys):
    code, _, err = _run(["run", "--set", "colour=red"], capsys)
    assert code == 2 and _one_line(err).endswith("'colour' is not a spec key")


def test_every_option_of_every_subcommand_has_help():
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    assert {c.dest for c in sub._choices_actions} == set(sub.choices)          # every subcommand has a help line
    missing = [f"demq {name} {'/'.join(a.option_strings) or a.dest}"
               for name, p in sub.choices.items() for a in p._actions if not a.help]
    assert missing == []


def _tiny_result(path) -> None:
    """A result with one snapshot frame of 4 spheres, written by the engine's writer (no simulation)."""
    from engine.output.h5md import H5MDWriter

    w = H5MDWriter(path, n=4, box_length=1.0, spec_json="{}", derived={}, radius=np.full(4, 0.1))
    w.snapshot(0, 0.0, {"position": np.random.default_rng(1).random((4, 3)), "velocity": np.zeros((4, 3))})
    w.finish({})


@pytest.mark.parametrize("umask", [0o022, 0o077])
def test_export_writes_its_file_with_the_mode_of_the_results(umask, tmp_path, capsys):
    """0666 less the umask, as the result writer (HDF5) creates its files: 0644 under the usual umask 022."""
    old = os.umask(umask)
    try:
        _tiny_result(tmp_path / "r.h5")
        code, out, _ = _run(["export", str(tmp_path / "r.h5")], capsys)
    finally:
        os.umask(old)
    assert code == 0 and out.strip() == f"wrote {tmp_path / 'r.gsd'}"
    mode = stat.S_IMODE((tmp_path / "r.gsd").stat().st_mode)
    assert mode == 0o666 & ~umask == stat.S_IMODE((tmp_path / "r.h5").stat().st_mode)


@pytest.mark.parametrize("argv, words", [
    (["export", "MISSING"], "no result file"),
    (["export", "JUNK"], "is not an HDF5 file"),
    (["export", "RESULT", "-o", "NO_DIR"], "' does not exist"),
    (["fetch", "0123abcd", "-o", "NO_DIR"], "' does not exist"),
    (["run", "-o", "DIR"], "it is a folder"),
])
def test_missing_files_and_folders_are_usage_errors(argv, words, tmp_path, capsys):
    (tmp_path / "junk.h5").write_text("not HDF5")
    _tiny_result(tmp_path / "r.h5")
    names = {"MISSING": tmp_path / "nonexistent.h5", "JUNK": tmp_path / "junk.h5", "RESULT": tmp_path / "r.h5",
             "NO_DIR": tmp_path / "no-such-folder" / "out", "DIR": tmp_path}
    code, _, err = _run([str(names.get(a, a)) for a in argv], capsys)
    assert code == 2 and err.startswith(f"demq {argv[0]}: ") and words in _one_line(err)


@pytest.mark.parametrize("argv, env, code, words", [
    (["status"], {"DEMQ_PORT": "abc"}, 2, "DEMQ_PORT='abc' is not a valid int"),
    (["status", "--local", "--database-url", "mysql://x"], {}, 2, "unsupported database URL 'mysql://x'"),
    pytest.param(["status", "--local", "--database-url", "postgresql://demq:secret@127.0.0.1:1/demq"], {}, 1,
                 "cannot open the job database postgresql://demq:***@127.0.0.1:1/demq (connection failed",
                 marks=pytest.mark.postgres, id="postgres-no-server"),
    (["status", "--local", "0123abcd"], {}, 1, "no job with id '0123abcd'"),
])
def test_settings_and_queue_errors_are_one_line(argv, env, code, words, tmp_path, capsys, monkeypatch):
    if "postgresql://" in " ".join(argv):
        postgres_driver()        # no server needed, the driver is: the postgres extra
    monkeypatch.chdir(tmp_path)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    got, _, err = _run(argv, capsys)
    assert got == code and words in _one_line(err) and "secret" not in err


@pytest.mark.parametrize("command", ["status", "worker"])
def test_a_postgres_url_without_the_driver_names_the_extra(command, tmp_path, capsys, monkeypatch):
    """The light install has no PostgreSQL driver: a postgresql:// URL stops with one line naming the extra."""
    hide_psycopg(monkeypatch)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DEMQ_DATABASE_URL", "postgresql://demq:secret@127.0.0.1:1/demq")
    argv = [command, "--local"] if command == "status" else [command]
    code, _, err = _run(argv, capsys)
    assert code == 2 and "secret" not in err
    assert _one_line(err).startswith(f"demq {command}: a PostgreSQL job queue (a postgresql:// database URL) "
                                     f"needs psycopg, which is not installed: {NO_POSTGRES}")


def test_serve_on_a_port_another_server_has_is_one_line(tmp_path, capsys):
    with socket.socket() as other:
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        code, _, err = _run(["serve", "--host", "127.0.0.1", "--port", str(port), "--data-dir", str(tmp_path)], capsys)
    assert code == 1
    assert _one_line(err) == (f"demq serve: cannot listen on 127.0.0.1:{port} (Address already in use); stop the "
                              f"server that has it or pick another port with --port/DEMQ_PORT")


def test_validate_refuses_a_report_that_needs_matplotlib_up_front(tmp_path, capsys, monkeypatch):
    hide_matplotlib(monkeypatch)
    code, _, err = _run(["validate", "hcs-spheres", "--quick", "-o", str(tmp_path / "rep")], capsys)
    assert code == 2
    assert _one_line(err).startswith("demq validate: the report of hcs-spheres (its figures) needs matplotlib")
    assert "pip install 'demq[plots]'" in err and not (tmp_path / "rep").exists()


def test_validate_sonine_on_the_light_install_prints_its_table_and_skips_the_picture(tmp_path, capsys, monkeypatch):
    """`demq validate sonine --quick` without matplotlib, through the command line, on 2 seeds of 64 spheres
    (the quick density) and a small DSMC instead of 6 x 800 and 20 000: the same code path in about 4 s."""
    hide_matplotlib(monkeypatch)
    monkeypatch.setattr(sonine, "main", functools.partial(sonine.main, n_particles=64, box_length=0.431,
                                                          dsmc_n=500))
    out_dir = tmp_path / "sonine"
    code, out, err = _run(["validate", "sonine", "--quick", "--seeds", "2", "--backend", "cpu", "-o", str(out_dir)],
                          capsys)
    (row,) = json.loads((out_dir / "summary.json").read_text())
    assert code == (0 if row["pass"] else 1)
    assert _one_line(err) == (f"demq validate sonine: no picture (sonine.png): matplotlib is not installed; the "
                              f"tables above and {out_dir / 'README.md'} hold the numbers; pip install "
                              f"'demq[plots]' draws it")
    assert "| e_n | a2 DEM | a2 DSMC (Boltzmann) |" in out and "| 0.4 | " in out
    readme = (out_dir / "README.md").read_text()
    assert "| 0.4 | " in readme and "![a2]" not in readme and "No picture" in readme
    assert not (out_dir / "sonine.png").exists()
