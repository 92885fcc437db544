"""bench/loop_ab.py's cases and variants: a packed case compared with one scene at the same start, and the variants
that switch the garbage collector off and back on."""

from __future__ import annotations

import gc

import pytest

from bench import loop_ab
from engine.setup.start_kind import start_protocol


def test_one_large_scene_and_packed_small_scenes_both_start_random_by_default_and_start_sets_them():
    one = loop_ab.extra_specs("elastic-1M-f64", 100, "cpu")
    packed = loop_ab.extra_specs("packed-256x4096-f64", 100, "cpu")
    assert len(one) == 1 and len(packed) == 256 and one[0].n_particles == 256 * packed[0].n_particles
    # a large one-size start is random too (placed in parallel, engine/setup/cell_rsa.py)
    assert start_protocol(one[0]) == "random" and start_protocol(packed[0]) == "random"
    for start in ("random", "lattice"):
        specs = loop_ab.extra_specs("elastic-1M-f64", 100, "cpu", start) + \
            loop_ab.extra_specs("packed-256x4096-f64", 100, "cpu", start)
        assert {start_protocol(s) for s in specs} == {start}
        assert all(s.thermalization == 0.0 and s.snapshots == 0 for s in specs)
    # the same sphere size and density: the box scales with N
    assert packed[0].box_length ** 3 * 256 == pytest.approx(one[0].box_length ** 3)
    # --phi reaches the sphere packs (in the same boxes), not the spheroids
    dense = loop_ab.case_specs("packed-64x4096-f64", 100, "cpu", phi=0.2)
    assert len(dense) == 64 and {s.volume_fraction for s in dense} == {0.2}
    assert dense[0].box_length == pytest.approx(packed[0].box_length)
    assert loop_ab.case_specs("spheroids-rough-1M-f64", 100, "cpu", phi=0.2)[0].volume_fraction == 0.05


def test_the_gc_off_variant_turns_the_collector_off_and_default_turns_it_back_on():
    import engine.loops.cuda_loop as loop

    blocks = loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM
    try:
        loop_ab.apply("gc_off", blocks)
        assert not gc.isenabled()
        loop_ab.apply("default", blocks)
        assert gc.isenabled()
    finally:
        gc.enable()
        loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM = blocks


def test_blocks_variants_set_the_force_and_observing_launch_bounds_and_default_restores_them():
    import engine.loops.cuda_loop as loop

    blocks = loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM
    try:
        loop_ab.apply("blocks=2+observe_blocks=3+kick_blocks=5", blocks)
        assert loop.FORCES_BLOCKS_PER_SM == {"*": 2} and loop.OBSERVE_BLOCKS_PER_SM == {"*": 3}
        assert loop.KICK_DRIFT_BLOCKS_PER_SM == {"*": 5}
        loop_ab.apply("observe_blocks=0", blocks)
        assert loop.FORCES_BLOCKS_PER_SM == blocks[0] and loop.OBSERVE_BLOCKS_PER_SM is None
        loop_ab.apply("default", blocks)
        assert (loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM) == blocks
    finally:
        loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM = blocks


def test_the_own_scratch_variant_gives_the_rebuild_its_own_scratch_and_default_lends_it_again():
    import engine.loops.cuda_loop as loop
    import engine.loops.cuda_rebuild as rebuild

    blocks = loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM
    try:
        loop_ab.apply("own_scratch", blocks)
        assert rebuild.LEND_SCRATCH is False
        loop_ab.apply("default", blocks)
        assert rebuild.LEND_SCRATCH is True
    finally:
        rebuild.LEND_SCRATCH = True
        loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM = blocks


def test_default_puts_back_each_switch_as_the_engine_had_it():
    """A switch's "on" is the engine's own value, not True: the sort interval's drift is a number of cells."""
    import engine.loops.cuda_ensemble as ensemble
    import engine.loops.cuda_loop as loop
    import engine.loops.cuda_rebuild as rebuild

    blocks = loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM
    drift, multistep = rebuild.SORT_DRIFT_CELLS, ensemble.MULTISTEP
    assert 0 < drift < 1
    try:
        loop_ab.apply("sort_interval+multistep", blocks)
        assert rebuild.SORT_DRIFT_CELLS == 0 and ensemble.MULTISTEP is False
        loop_ab.apply("default", blocks)
        assert rebuild.SORT_DRIFT_CELLS == drift and ensemble.MULTISTEP is multistep
    finally:
        rebuild.SORT_DRIFT_CELLS, ensemble.MULTISTEP = drift, multistep
        loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM = blocks


def test_the_skin_variant_is_a_spec_field_not_a_switch():
    """``skin=L`` sets every scene's verlet_skin (and turns no switch off); the other variants leave the default."""
    import engine.loops.cuda_loop as loop

    assert loop_ab.variant_skin("gc_off+skin=0.12") == 0.12 and loop_ab.variant_skin("default") is None
    blocks = loop.FORCES_BLOCKS_PER_SM, loop.OBSERVE_BLOCKS_PER_SM, loop.KICK_DRIFT_BLOCKS_PER_SM
    try:
        loop_ab.apply("skin=0.12", blocks)        # an unknown switch name would raise here
    finally:
        loop_ab.apply("default", blocks)
    assert [s.verlet_skin for s in loop_ab.case_specs("rough-2M-f64", 100, skin=0.12)] == [0.12]
    assert {s.verlet_skin for s in loop_ab.case_specs("packed-256x4096-f64", 100, skin=0.3)} == {0.3}
    assert loop_ab.case_specs("rough-2M-f64", 100)[0].verlet_skin is None


def test_case_specs_scale_the_box_with_n_and_keep_the_step():
    """``n``: the same sphere radius, so the same dt and t_end; ``velocity_rms``: the same dt, a faster gas."""
    from engine.setup.params import derive

    base = loop_ab.case_specs("rough-2M-f64", 100)[0]
    small = loop_ab.case_specs("rough-2M-f64", 100, n=32768)[0]
    fast = loop_ab.case_specs("rough-2M-f64", 100, velocity_rms=8.0)[0]
    p0, p1, p2 = derive(base), derive(small), derive(fast)
    assert small.n_particles == 32768 and p1.radius == pytest.approx(p0.radius, rel=1e-12)
    assert (small.dt, small.t_end) == (base.dt, base.t_end) and p1.n_steps == p0.n_steps == 100
    assert fast.velocity_rms == 8.0 and fast.dt == base.dt and p2.radius == p0.radius


class _Event:
    """A stand-in CUDA event whose elapsed time to another is the difference of their stamps (ms)."""

    def __init__(self, stamp: float):
        self.stamp = stamp

    def synchronize(self) -> None:
        pass

    def elapsed_time(self, other: "_Event") -> float:
        return other.stamp - self.stamp


def test_rebuild_parts_leave_out_the_first_build_and_give_the_rest_of_a_rebuild_to_build():
    """RebuildParts.summary: per rebuild of the loop (the job's first build, before the loop, left out), each timed
    part, the whole, and ``build`` = the whole less the timed parts; the kernels launched inside the loop's
    rebuilds by name (their "/..." suffix dropped), per rebuild."""
    timer = loop_ab.RebuildParts()
    for k, scale in enumerate((100.0, 1.0, 3.0)):     # the first build is slow (setup), the two loop ones are not
        t = 10.0 * k
        parts = {"_compact": 0.5, "_sort_and_permute": 1.0, "_fill_history": 0.25}
        for name, ms in parts.items():
            timer.marks.append((name, _Event(t), _Event(t + scale * ms)))
        timer.marks.append(("_gpu_rebuild", _Event(t), _Event(t + scale * 4.0)))
        timer.host_s.append(scale * 5e-3)
        timer.launches.append((k, f"gather_rows/{k}/0", _Event(t), _Event(t + scale * 0.5)))
    out = timer.summary()
    assert out["rebuilds"] == 2
    assert out["compact"] == 1.0 and out["sort_and_permute"] == 2.0 and out["fill_history"] == 0.5
    assert out["rebuild"] == 8.0 and out["build"] == 4.5 and out["host_ms"] == 10.0
    assert out["kernels"] == {"gather_rows": 1.0}
    assert loop_ab.RebuildParts().summary() == {"rebuilds": 0}


def test_host_parts_time_the_loops_host_pieces_and_put_every_method_back():
    """HostParts (``--host-parts``): inside it the GPU loop's host pieces, the launches by kernel name and the direct
    driver calls are timed (each call once, its result passed through, a launch's "/..." suffix dropped); the summary
    is µs a step over the run's steps, the largest first; on leaving, every patched attribute is the object it was
    (an inherited method is inherited again)."""
    import engine.loops.cuda_ensemble as ensemble
    import engine.loops.cuda_launch as launch
    import engine.numba_support.numba_internals as internals

    base = ensemble.CudaEnsembleBase
    before = {name: base.__dict__.get(name) for name in loop_ab.HostParts.METHODS}
    launch_before, direct_before = launch.LaunchCache.__dict__["launch"], internals.direct_launch
    calls = []
    with loop_ab.HostParts() as host:
        assert all(base.__dict__.get(name) is not None for name in loop_ab.HostParts.METHODS)
        cache = launch.LaunchCache(enabled=False)
        cache.launch("gather_rows/pos/0", {(1, 32, None): lambda *a: calls.append("launched")}, (1, 32, None), ())
        host._timed("_collect", lambda x: calls.append(x) or x)(7)
        assert internals.direct_launch(None, ((1, 1, 1), (1, 1, 1), True), None, [], []) == "a cooperative kernel"
    assert calls == ["launched", 7] and set(host.seconds) == {"launch:gather_rows", "_collect"}
    assert {name: base.__dict__.get(name) for name in loop_ab.HostParts.METHODS} == before
    assert launch.LaunchCache.__dict__["launch"] is launch_before and internals.direct_launch is direct_before
    host.seconds = {"a": 1e-3, "b": 4e-3}
    assert list(host.summary(100).items()) == [("b", 40.0), ("a", 10.0)]
