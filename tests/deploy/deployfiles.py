"""Readers of the files in deploy/ (compose file, Dockerfiles, Slurm script, systemd units), and the
`demq` command lines they run, so the process tests can run exactly those command lines.

A command line here is a tuple of argv words, e.g. ``("demq", "worker", "--exit-when-idle")``.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import stat
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
COMPOSE = DEPLOY / "compose.yaml"
API_DOCKERFILE = DEPLOY / "docker" / "api.Dockerfile"
WORKER_DOCKERFILE = DEPLOY / "docker" / "worker.Dockerfile"
DOCKERFILES = (API_DOCKERFILE, WORKER_DOCKERFILE)
SBATCH = DEPLOY / "slurm" / "demq-worker.sbatch"
WORKSTATION_UNIT = DEPLOY / "systemd" / "demq.service"
WORKER_UNIT = DEPLOY / "systemd" / "demq-worker@.service"
UNITS = (WORKSTATION_UNIT, WORKER_UNIT)
UNIT_ENV = DEPLOY / "systemd" / "demq.env"
DOCS = ROOT / "docs" / "scaling-out.md"


# ---- compose ------------------------------------------------------------------------------------------
def compose() -> dict:
    with open(COMPOSE) as f:
        return yaml.safe_load(f)


def compose_workers(doc: dict | None = None) -> dict[str, dict]:
    doc = doc or compose()
    return {name: svc for name, svc in doc["services"].items() if name.startswith("worker")}


# ---- Dockerfiles --------------------------------------------------------------------------------------
def dockerfile(path: Path) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs; comments dropped, continuation lines joined."""
    out, buf = [], ""
    for line in path.read_text().splitlines():
        stripped = line.strip()
        if not buf and (not stripped or stripped.startswith("#")):
            continue
        if buf and stripped.startswith("#"):
            continue  # a comment inside a continued instruction
        if stripped.endswith("\\"):
            buf += stripped[:-1] + " "
            continue
        buf += stripped
        word, _, rest = buf.partition(" ")
        out.append((word.upper(), rest.strip()))
        buf = ""
    assert not buf, f"{path}: unterminated continuation line"
    return out


def instruction_argv(arguments: str) -> tuple[str, ...]:
    """Exec form (a JSON array) or shell form of CMD/ENTRYPOINT/HEALTHCHECK CMD."""
    if arguments.startswith("["):
        return tuple(json.loads(arguments))
    return tuple(shlex.split(arguments))


def dockerfile_cmd(path: Path) -> tuple[str, ...]:
    cmds = [a for i, a in dockerfile(path) if i == "CMD"]
    assert len(cmds) == 1, f"{path}: expected one CMD"
    return instruction_argv(cmds[0])


def dockerfile_healthcheck(path: Path) -> tuple[str, ...]:
    checks = [a for i, a in dockerfile(path) if i == "HEALTHCHECK"]
    assert len(checks) == 1, f"{path}: expected one HEALTHCHECK"
    _, _, command = checks[0].partition(" CMD ")
    return instruction_argv(command.strip())


# ---- Slurm --------------------------------------------------------------------------------------------
def sbatch_directives() -> dict[str, str]:
    """``#SBATCH --key=value`` lines of the script header -> {key: value}."""
    out = {}
    for line in SBATCH.read_text().splitlines():
        m = re.match(r"#SBATCH\s+--([\w-]+)(?:[= ](.*))?$", line.strip())
        if m:
            out[m.group(1)] = (m.group(2) or "").strip()
    return out


def sbatch_exec() -> tuple[str, ...]:
    """The argv of the script's (single, final) ``exec`` line."""
    lines = [ln.strip() for ln in SBATCH.read_text().splitlines() if ln.strip() and not ln.strip().startswith("#")]
    execs = [ln for ln in lines if ln.startswith("exec ")]
    assert len(execs) == 1 and lines[-1] == execs[0], "the script must end in exactly one exec line"
    return tuple(shlex.split(execs[0])[1:])


# ---- systemd ------------------------------------------------------------------------------------------
def unit(path: Path) -> dict[str, dict[str, list[str]]]:
    """A unit file -> {section: {key: [values]}} (keys may repeat, e.g. Environment=)."""
    sections: dict[str, dict[str, list[str]]] = {}
    current = None
    for line in path.read_text().splitlines():
        s = line.strip()
        if not s or s[0] in "#;":
            continue
        if s.startswith("[") and s.endswith("]"):
            current = sections.setdefault(s[1:-1], {})
            continue
        key, sep, value = s.partition("=")
        assert sep and current is not None, f"{path}: cannot parse {line!r}"
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


def unit_exec(path: Path) -> tuple[str, ...]:
    """ExecStart of a unit as a command line with the binary's basename (``/opt/.../demq`` -> ``demq``)."""
    (start,) = unit(path)["Service"]["ExecStart"]
    argv = shlex.split(start)
    return (os.path.basename(argv[0]), *argv[1:])


def env_file(path: Path = UNIT_ENV) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines():
        s = line.strip()
        if s and not s.startswith("#"):
            key, _, value = s.partition("=")
            out[key] = value
    return out


def seconds(value: str) -> float:
    """systemd/compose durations: ``120``, ``90s``, ``2min``, ``1m30s``."""
    total, units = 0.0, {"": 1, "s": 1, "sec": 1, "m": 60, "min": 60, "h": 3600}
    parts = re.findall(r"(\d+(?:\.\d+)?)\s*([a-z]*)", value)
    assert parts, value
    for number, unit_ in parts:
        total += float(number) * units[unit_]
    return total


# ---- every demq command line in deploy/ ---------------------------------------------------------------
def deploy_command_lines() -> dict[str, tuple[str, ...]]:
    """Where each `demq ...` (and healthcheck) command line of deploy/ comes from -> its argv."""
    doc = compose()
    found = {
        "compose api command": tuple(doc["services"]["api"]["command"]),
        "compose api healthcheck": tuple(doc["services"]["api"]["healthcheck"]["test"][1:]),
        "api.Dockerfile CMD": dockerfile_cmd(API_DOCKERFILE),
        "api.Dockerfile HEALTHCHECK": dockerfile_healthcheck(API_DOCKERFILE),
        "worker.Dockerfile CMD": dockerfile_cmd(WORKER_DOCKERFILE),
        "worker.Dockerfile HEALTHCHECK": dockerfile_healthcheck(WORKER_DOCKERFILE),
        "slurm exec": sbatch_exec(),
        "demq.service ExecStart": unit_exec(WORKSTATION_UNIT),
        "demq-worker@.service ExecStart": unit_exec(WORKER_UNIT),
    }
    for name, svc in compose_workers(doc).items():
        found[f"compose {name} command"] = tuple(svc["command"])
        found[f"compose {name} healthcheck"] = tuple(svc["healthcheck"]["test"][1:])
    return found


# ---- running them here --------------------------------------------------------------------------------
def shim_bin(directory: Path) -> Path:
    """A directory with ``demq`` (= ``python -m service.cli`` of this checkout, like the console
    script pyproject.toml installs) and ``python`` (this interpreter), to put first on PATH."""
    directory.mkdir(parents=True, exist_ok=True)
    demq = directory / "demq"
    demq.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m service.cli "$@"\n')
    demq.chmod(demq.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    python = directory / "python"
    if not python.exists():
        python.symlink_to(sys.executable)
    return directory


def clean_env(bin_dir: Path, **env: str) -> dict[str, str]:
    """The test's environment without DEMQ_* settings, the shims first on PATH, the checkout importable."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("DEMQ_")}
    base.update(PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}", PYTHONPATH=str(ROOT))
    base.update(env)
    return base
