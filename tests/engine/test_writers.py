"""The output writers' triggers and the records writer's energy check (engine/output/writers/)."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from engine.errors import InstabilityError
from engine.output.writers.records import ENERGY_RISE_TOLERANCE, RecordWriter
from engine.output.writers.snapshots import snapshot_steps
from engine.output.writers.triggers import AtSteps, Periodic, WallClock


def test_periodic_trigger_fires_every_period_and_at_the_last_step():
    t = Periodic(4, 10)
    assert t.steps() == {0, 4, 8, 10}
    assert [s for s in range(12) if t(s)] == [0, 4, 8, 10]
    with pytest.raises(ValueError, match="period = 0"):
        Periodic(0, 10)


def test_snapshot_steps_spread_over_the_run():
    assert snapshot_steps(100, 0) == set() and snapshot_steps(100, 1) == {100}
    assert snapshot_steps(100, 3) == {0, 50, 100}
    t = AtSteps(snapshot_steps(10, 4))
    assert t.steps() == {0, 3, 7, 10} and t(7) and not t(6)


def test_wall_clock_without_an_interval_is_never_due():
    assert not WallClock(None).due()
    clock = WallClock(0.0)
    assert clock.due()


class _File:
    def __init__(self):
        self.rows = []

    def observables(self, step, t, values):
        self.rows.append(step)


def _obs(e):
    return {"kinetic_energy_translational": e, "kinetic_energy_rotational": 0.0, "elastic_energy": 0.0,
            "contacts": 0, "max_overlap": 0.0}


def test_records_writer_records_its_steps_and_stops_a_dissipative_run_whose_energy_rises():
    p = SimpleNamespace(output_every=5, n_steps=12, dt=1e-4, contact_time=5e-3)
    f = _File()
    w = RecordWriter(p, 10, dissipative=True)
    assert w.prev_energy == math.inf
    for step, e in ((0, 1.0), (3, 5.0), (5, 0.8), (10, 0.8 * (1 + ENERGY_RISE_TOLERANCE) * 0.999)):
        w.write(f, step, step * p.dt, _obs(e))
    assert f.rows == [0, 5, 10] and w.prev_energy == 0.8       # step 3 is no record step: not written, not checked
    with pytest.raises(InstabilityError, match="total energy rose .* by step 12"):
        w.write(f, 12, 12 * p.dt, _obs(0.8 * (1 + 2 * ENERGY_RISE_TOLERANCE)))
    elastic = RecordWriter(p, 10, dissipative=False)
    for step in (0, 5):
        elastic.write(f, step, 0.0, _obs(1.0 + step))             # no check without dissipation
    assert np.isclose(elastic.prev_energy, 1.0)
