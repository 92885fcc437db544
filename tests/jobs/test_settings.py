"""Configuration: defaults, DEMQ_* variables, flags over variables, checks."""

from __future__ import annotations

from pathlib import Path

import pytest

from jobs.settings import Settings
from jobs.stores import open_store


def test_defaults_and_derived_paths():
    s = Settings.from_env(environ={})
    assert s.data_dir == Path("demq-data").absolute()
    assert s.database_url == f"sqlite:///{s.data_dir / 'demq.sqlite3'}"
    assert s.token is None and s.max_attempts == 3 and s.lease_s > s.heartbeat_s
    assert s.result_path("abc") == s.data_dir / "results" / "abc.h5"
    assert s.checkpoint_dir("abc") == s.data_dir / "checkpoints" / "abc"


def test_environment_then_flags():
    env = {"DEMQ_DATA_DIR": "/srv/demq", "DEMQ_TOKEN": "t", "DEMQ_MAX_PARTICLE_STEPS": "1e9",
           "DEMQ_LEASE_SECONDS": "30", "DEMQ_MAX_ATTEMPTS": "5", "DEMQ_PORT": "9000"}
    s = Settings.from_env(environ=env, max_attempts=2, port=None)
    assert s.data_dir == Path("/srv/demq") and s.token == "t" and s.max_particle_steps == 1e9
    assert s.lease_s == 30.0 and s.max_attempts == 2 and s.port == 9000


def test_bad_values_are_named():
    with pytest.raises(ValueError, match="DEMQ_LEASE_SECONDS='soon'"):
        Settings.from_env(environ={"DEMQ_LEASE_SECONDS": "soon"})
    with pytest.raises(ValueError, match="shorter than the lease"):
        Settings.from_env(environ={}, heartbeat_s=60, lease_s=30)
    with pytest.raises(ValueError, match="unsupported database URL"):
        open_store("mysql://x")
    with pytest.raises(ValueError, match="needs a file"):
        open_store("sqlite:///:memory:")


def test_worker_standby_setting(monkeypatch):
    import engine.driver.startup

    assert Settings.from_env(environ={"DEMQ_WORKER_STANDBY": "on"}).standby_enabled
    assert not Settings.from_env(environ={"DEMQ_WORKER_STANDBY": "0"}).standby_enabled
    import jobs.settings

    monkeypatch.setattr(jobs.settings.os, "cpu_count", lambda: 1)
    monkeypatch.setattr(engine.driver.startup, "nvidia_driver", lambda: True)
    assert Settings.from_env(environ={}).standby_enabled           # auto: where an NVIDIA driver is ...
    monkeypatch.setattr(engine.driver.startup, "nvidia_driver", lambda: False)
    assert not Settings.from_env(environ={}).standby_enabled
    monkeypatch.setattr(jobs.settings.os, "cpu_count", lambda: 2)
    assert Settings.from_env(environ={}).standby_enabled           # ... or more than one CPU core
    with pytest.raises(ValueError, match="DEMQ_WORKER_STANDBY = 'maybe' must be one of auto, on, off"):
        Settings.from_env(environ={"DEMQ_WORKER_STANDBY": "maybe"})
