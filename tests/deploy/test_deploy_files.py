"""The deployment files, checked as far as a machine without a Docker engine, Slurm or systemd as
init allows: they parse, they are consistent with each other and with the settings, and every
command line they run is one that the process tests in this directory run."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
from packaging.requirements import Requirement

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from jobs.settings import _ENV as SETTINGS_ENV
from jobs.settings import Settings
from tests.deploy.deployfiles import (API_DOCKERFILE, COMPOSE, DEPLOY, DOCKERFILES, DOCS, ROOT, SBATCH, UNIT_ENV,
                                      UNITS, WORKER_DOCKERFILE, WORKER_UNIT, WORKSTATION_UNIT, compose,
                                      compose_workers, deploy_command_lines, dockerfile, env_file,
                                      sbatch_directives, seconds, shim_bin, unit)

API_HEALTHCHECK = ("python", "-c", "import os, urllib.request; urllib.request.urlopen("
                   "'http://127.0.0.1:%s/healthz' % os.environ.get('DEMQ_PORT', '8000'), timeout=4)")
#: Every command line of deploy/ -> the test that runs exactly it as a process.
EXERCISED = {
    ("demq", "serve", "--no-worker"): "test_scale_out (the API)",
    ("demq", "worker"): "test_scale_out (the SIGTERM and SIGKILL workers)",
    ("demq", "worker", "--exit-when-idle"): "test_scale_out, test_graceful_shutdown (via the sbatch script)",
    ("demq", "serve"): "test_graceful_shutdown (systemd workstation unit)",
    ("demq", "status", "--local", "--limit", "1"): "test_worker_healthcheck_command_runs (below)",
    API_HEALTHCHECK: "test_scale_out (compose API healthcheck)",
}


def test_every_command_line_in_deploy_is_exercised():
    found = deploy_command_lines()
    unexercised = {where: argv for where, argv in found.items() if argv not in EXERCISED}
    assert unexercised == {}, unexercised
    assert set(found.values()) == set(EXERCISED), "an entry of EXERCISED no longer appears in deploy/"


# ---- compose ------------------------------------------------------------------------------------------
def test_compose_file_parses_and_wires_postgres_api_and_one_worker_per_gpu():
    doc = compose()
    services = doc["services"]
    assert {"postgres", "api"} <= set(services)
    workers = compose_workers(doc)
    assert len(workers) >= 2
    gpus = []
    for name, w in workers.items():
        (device,) = w["deploy"]["resources"]["reservations"]["devices"]
        assert device["driver"] == "nvidia" and device["capabilities"] == ["gpu"] and len(device["device_ids"]) == 1
        gpus += device["device_ids"]
        assert name == f"worker-gpu{device['device_ids'][0]}"
    assert len(set(gpus)) == len(gpus), "each worker gets its own GPU"

    data_mounts = set()
    for name in ["api", *workers]:
        svc = services[name]
        env = svc["environment"]
        assert env["DEMQ_DATABASE_URL"].startswith("postgresql://") and "@postgres:5432/" in env["DEMQ_DATABASE_URL"]
        volume, _, path = svc["volumes"][0].partition(":")
        assert path == env["DEMQ_DATA_DIR"], f"{name}: the result volume is the data directory"
        data_mounts.add((volume, path))
        assert svc["depends_on"]["postgres"]["condition"] == "service_healthy"
        assert svc["stop_signal"] == "SIGTERM" and svc["init"] is True
        assert set(env) <= set(SETTINGS_ENV.values()), f"{name}: unknown DEMQ_ variables"
        build = svc["build"]
        assert (COMPOSE.parent / build["context"]).resolve() == ROOT
        assert (ROOT / build["dockerfile"]).is_file()
        assert svc["healthcheck"]["test"][0] == "CMD"
    assert len(data_mounts) == 1 and next(iter(data_mounts))[0] in doc["volumes"], "one shared result volume"
    for name, w in workers.items():
        grace = seconds(w["stop_grace_period"])
        cancel = float(w["environment"]["DEMQ_CANCEL_GRACE_SECONDS"].split(":-")[1].rstrip("}"))
        assert grace > cancel + 10, f"{name}: stop_grace_period must exceed the cancel grace"
        assert w["build"]["dockerfile"] == str(WORKER_DOCKERFILE.relative_to(ROOT))
    assert services["api"]["build"]["dockerfile"] == str(API_DOCKERFILE.relative_to(ROOT))
    password = services["postgres"]["environment"]["POSTGRES_PASSWORD"]
    assert password.startswith("${DEMQ_DB_PASSWORD:?"), "no default database password"


def test_compose_config_with_the_docker_client_when_it_has_compose():
    """`docker compose config` parses and interpolates without an engine; run it where the client has
    the compose plugin (this machine's client has none, so PyYAML above is the check here)."""
    docker = shutil.which("docker")
    if docker is None or subprocess.run([docker, "compose", "version"], capture_output=True).returncode != 0:
        return
    r = subprocess.run([docker, "compose", "-f", str(COMPOSE), "config", "--quiet"], capture_output=True, text=True,
                       env={"PATH": "/usr/bin:/bin:/usr/local/bin", "DEMQ_DB_PASSWORD": "x"}, timeout=60)
    assert r.returncode == 0, r.stderr


# ---- Dockerfiles --------------------------------------------------------------------------------------
@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_sources_exist_and_are_not_ignored(path):
    ignore = (path.parent / f"{path.name}.dockerignore").read_text().splitlines()
    allowed = [ln[1:].rstrip("/") for ln in ignore if ln.startswith("!")]
    assert "**" in ignore, "the ignore file starts from nothing"
    copies = [args for instr, args in dockerfile(path) if instr == "COPY"]
    assert copies
    for args in copies:
        words = [w for w in args.split() if not w.startswith("--")]
        *sources, dest = words
        assert dest.startswith("/")
        for src in sources:
            assert (ROOT / src).exists(), f"{path.name}: COPY source {src} does not exist"
            assert src.rstrip("/") in allowed, f"{path.name}: COPY source {src} is excluded by the .dockerignore"


@pytest.mark.parametrize("path", DOCKERFILES, ids=lambda p: p.name)
def test_dockerfile_structure(path):
    instrs = dockerfile(path)
    names = [i for i, _ in instrs]
    assert names.count("FROM") == 1 and names.count("CMD") == 1 and "ENTRYPOINT" not in names
    assert ("STOPSIGNAL", "SIGTERM") in instrs
    user = [a for i, a in instrs if i == "USER"]
    assert user and user[-1] not in ("root", "0"), "run as an unprivileged user"
    run = " ".join(a for i, a in instrs if i == "RUN")
    assert re.search(r"pip install --constraint /src/deploy/docker/constraints.txt .*/src\b", run)
    env = " ".join(a for i, a in instrs if i == "ENV")
    assert "DEMQ_DATA_DIR=/data" in env and ("VOLUME", '["/data"]') in instrs


def test_worker_image_is_cuda_with_pinned_numba_cuda_and_api_image_is_not():
    instrs = dict((i, a) for i, a in dockerfile(WORKER_DOCKERFILE) if i in ("ARG", "FROM") and "CUDA_IMAGE" in a)
    image = instrs["ARG"].partition("=")[2]
    assert re.fullmatch(r"nvidia/cuda:1[23]\.\d+\.\d+-runtime-ubuntu2[24]\.04", image), image
    assert instrs["FROM"] == "${CUDA_IMAGE}"
    assert "numba-cuda[${NUMBA_CUDA_EXTRA}]" in WORKER_DOCKERFILE.read_text()
    assert "ARG NUMBA_CUDA_EXTRA=cu12" in WORKER_DOCKERFILE.read_text()
    (api_from,) = [a for i, a in dockerfile(API_DOCKERFILE) if i == "FROM"]
    assert re.fullmatch(r"python:3\.1[12]-slim-\w+", api_from), api_from

    pins = {}
    for line in (DEPLOY / "docker" / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            req = Requirement(line)
            pins[req.name] = next(iter(req.specifier)).version
    assert pins["numpy"] == "2.3.5" and pins["numba"].startswith("0.68.") and pins["numba-cuda"].startswith("0.30.")
    deps = {Requirement(d).name: Requirement(d) for d in
            tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]}
    for name, version in pins.items():
        assert deps[name].specifier.contains(version), f"pin {name}=={version} outside pyproject's {deps[name]}"


# ---- Slurm --------------------------------------------------------------------------------------------
def test_slurm_script_one_gpu_per_array_task_sigterm_before_the_limit():
    assert subprocess.run(["bash", "-n", str(SBATCH)]).returncode == 0
    assert SBATCH.read_text().startswith("#!/bin/bash\n")
    d = sbatch_directives()
    assert re.fullmatch(r"\d+-\d+(%\d+)?", d["array"])
    assert d["gres"] == "gpu:1" and d["ntasks"] == "1"
    m = re.fullmatch(r"B:TERM@(\d+)", d["signal"])
    assert m and int(m.group(1)) > Settings().cancel_grace_s + 30, "SIGTERM early enough to release the job"
    text = SBATCH.read_text()
    for var in ("DEMQ_DATABASE_URL", "DEMQ_DATA_DIR"):
        assert f'"${{{var}:?' in text, f"the script insists on {var}"
    if shutil.which("shellcheck"):
        r = subprocess.run(["shellcheck", str(SBATCH)], capture_output=True, text=True)
        assert r.returncode == 0, r.stdout


def test_slurm_script_refuses_to_start_without_the_shared_queue(tmp_path):
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    r = subprocess.run(["bash", str(SBATCH)], env=env, capture_output=True, text=True, timeout=30)
    assert r.returncode != 0 and "DEMQ_DATABASE_URL" in r.stderr


# ---- systemd ------------------------------------------------------------------------------------------
def test_systemd_units_stop_gracefully_and_bind_gpus():
    env = env_file()
    cancel = float(env["DEMQ_CANCEL_GRACE_SECONDS"])
    assert set(env) <= set(SETTINGS_ENV.values())
    for path in UNITS:
        svc = unit(path)["Service"]
        assert svc["KillSignal"] == ["SIGTERM"] and svc["KillMode"] == ["mixed"]
        assert seconds(svc["TimeoutStopSec"][0]) > cancel + 30
        assert svc["EnvironmentFile"] == ["/etc/demq/demq.env"]
        assert svc["Restart"] == ["on-failure"]
        assert unit(path)["Install"]["WantedBy"] == ["multi-user.target"]
    assert "CUDA_VISIBLE_DEVICES=%i" in unit(WORKER_UNIT)["Service"]["Environment"]
    assert "CUDA_VISIBLE_DEVICES=0" in unit(WORKSTATION_UNIT)["Service"]["Environment"]
    assert env["DEMQ_DATA_DIR"] == "/var/lib/demq" == unit(WORKSTATION_UNIT)["Service"]["WorkingDirectory"][0]


def test_systemd_analyze_verify(tmp_path):
    """`systemd-analyze verify` on the units (ExecStart pointed at this checkout's demq)."""
    tool = shutil.which("systemd-analyze")
    if tool is None:
        return  # checked by the parser above
    demq = shim_bin(tmp_path / "bin") / "demq"
    units = []
    for path in UNITS:
        name = path.name.replace("@.", "@1.")
        target = tmp_path / name
        target.write_text(path.read_text().replace("/opt/demq/venv/bin/demq", str(demq)))
        units.append(str(target))
    r = subprocess.run([tool, "verify", *units], capture_output=True, text=True, timeout=60)
    # verify exits 0 even on unparsable settings (it logs and ignores them): every output line is a problem
    problems = [ln for ln in (r.stdout + r.stderr).splitlines() if ln.strip()]
    assert r.returncode == 0 and problems == [], r.stdout + r.stderr


# ---- health checks, documentation, test dependencies --------------------------------------------------
@pytest.mark.postgres
def test_worker_healthcheck_command_runs(tmp_path, bin_dir):
    """The worker containers' health check (`demq status --local --limit 1`): 0 when the job table
    answers, non-zero when it does not."""
    from tests.deploy.deployfiles import clean_env
    from tests.jobs.conftest import postgres_url

    argv = [a for a in deploy_command_lines()["worker.Dockerfile HEALTHCHECK"]]
    ok = subprocess.run(argv, env=clean_env(bin_dir, DEMQ_DATABASE_URL=postgres_url(), DEMQ_TABLE_PREFIX="hc_"),
                        capture_output=True, text=True, timeout=120)
    bad = subprocess.run(argv, env=clean_env(bin_dir, DEMQ_DATABASE_URL="postgresql://nobody@127.0.0.1:1/none"),
                         capture_output=True, text=True, timeout=120)
    from jobs.stores import open_store
    open_store(postgres_url(), "hc_").drop_tables()
    assert ok.returncode == 0, ok.stderr
    assert bad.returncode != 0


def test_docs_table_lists_every_setting_and_every_variable_deploy_uses():
    docs = DOCS.read_text()
    table = {m.group(1) for m in re.finditer(r"^\| `([A-Z_]+)`", docs, re.M)}
    missing = set(SETTINGS_ENV.values()) - table
    assert not missing, f"settings missing from the configuration table of {DOCS.name}: {missing}"
    used = set()
    for path in [COMPOSE, SBATCH, UNIT_ENV, *UNITS, *DOCKERFILES]:
        used |= set(re.findall(r"\b((?:DEMQ|NUMBA|CUDA|XDG|SLURM)_[A-Z_]+)", path.read_text()))
    used -= {"SLURM_ARRAY_JOB_ID", "SLURM_ARRAY_TASK_ID", "SLURM_JOB_ID", "SLURM_CPUS_PER_TASK", "CUDA_IMAGE",
             "NUMBA_CUDA_EXTRA"}  # build args, Slurm-set
    assert not used - table, f"variables used in deploy/ but not in the table: {used - table}"
    for needle in ("Scaling out", "demq worker --exit-when-idle", "<data_dir>/results/<job_id>.h5",
                   "checkpoints/<job_id>/", "SIGTERM", "docker compose -f deploy/compose.yaml",
                   "sbatch --array"):
        assert needle in docs, needle


def test_pyyaml_is_in_the_test_extra():
    extra = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["test"]
    assert any(Requirement(r).name.lower() == "pyyaml" for r in extra)
