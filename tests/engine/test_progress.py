"""The progress of `demq run` / `demq submit --wait`: a tqdm bar with its fields on a terminal, plain lines
elsewhere."""

from __future__ import annotations

import fcntl
import io
import os
import pty
import struct
import termios
import subprocess
import sys
from pathlib import Path

from engine.driver.progress import ProgressBar

ROOT = Path(__file__).resolve().parents[2]
RUN = [sys.executable, "-m", "service.cli", "run", "--backend", "cpu", "--set", "n_particles=64",
       "--set", "volume_fraction=0.05", "--set", "box_length=0.5", "--set", "t_end=0.05",
       "--set", "thermalization=0.2", "--set", "snapshots=1"]


def test_bar_shows_n_steps_per_second_cundall_and_eta():
    out = io.StringIO()
    bar = ProgressBar(4096, desc="demq run ", stream=out, disable=False)
    bar.update(0.25, "cooling", eta_s=75.0, cundall=8.192e6)
    bar.close()
    text = out.getvalue()
    assert "25.0%" in text and "N=4096" in text and "2e+03 steps/s" in text     # 8.192e6 / 4096 = 2000
    assert "Cundall 8.19e+06" in text and "ETA 01:15" in text and "cooling" in text


def test_bar_is_silent_when_the_stream_is_not_a_terminal():
    out = io.StringIO()                                   # isatty() is False
    bar = ProgressBar(64, stream=out)
    assert not bar.enabled
    bar.update(0.5, "cooling", 1.0, 1e6)
    bar.close()
    assert out.getvalue() == ""


def test_demq_run_progress_bar_on_a_terminal_and_lines_in_a_pipe(tmp_path):
    env = dict(os.environ, NUMBA_NUM_THREADS="1", COLUMNS="160")
    # stderr to a pipe: no bar, no carriage returns: the estimate, then plain progress lines ending at 100 %
    piped = subprocess.run(RUN + ["-o", str(tmp_path / "a.h5")], cwd=ROOT, env=env, capture_output=True, text=True,
                           timeout=300)
    assert piped.returncode == 0, piped.stderr
    assert "\r" not in piped.stderr and "wrote" in piped.stdout
    lines = piped.stderr.splitlines()
    assert lines[0].startswith("demq run: N = 64, ") and "particle-steps" in lines[0], lines
    progress = [line for line in lines if line.startswith("demq run: ") and "%" in line]
    assert progress and "100.0%" in progress[-1] and "N=64" in progress[-1], lines
    assert (tmp_path / "a.xmf").is_file()                  # the result's ParaView sidecar beside it
    # stderr on a pseudo-terminal: the tqdm bar with its fields
    primary, secondary = pty.openpty()
    fcntl.ioctl(secondary, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 160, 0, 0))   # a 160-column terminal
    proc = subprocess.Popen(RUN + ["-o", str(tmp_path / "b.h5")], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=secondary, stdin=subprocess.DEVNULL)
    os.close(secondary)
    chunks = []
    while True:
        try:
            data = os.read(primary, 65536)
        except OSError:                                   # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    assert proc.wait(timeout=300) == 0
    os.close(primary)
    text = b"".join(chunks).decode(errors="replace")
    assert "100.0%" in text and "N=64" in text and "steps/s" in text and "Cundall" in text, text[-500:]
