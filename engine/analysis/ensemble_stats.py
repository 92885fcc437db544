"""Statistics over seeds: the mean cooling curve and its standard error, and the batch-level HDF5 file.

A batch of runs is split into *groups* of equal specs apart from the seed (and the backend, which
changes nothing but rounding); in each group the runs share their record steps, and per record

    mean  = (1/K) sum_k x_k,        standard_error = s / sqrt(K),  s^2 = (1/(K-1)) sum_k (x_k - mean)^2

for x = T_tr, T_rot (J, per degree of freedom, as in the run files), E_tr/E_tr(0) (each run
normalised by its own first record) and the velocity-distribution cumulants sonine_a2_translational,
sonine_a2_rotational, sonine_a11 (dimensionless, engine/physics/sonine.py; a run file written before
the engine recorded them has none: its values are NaN). K = 1 has no spread estimate: its standard error is NaN.
The per-seed cumulant is a ratio of sums over N particles (bias O(1/N), far below the seed scatter).

Batch file layout (``write_batch_result``)::

    /                       @batch_id, @creator, @creator_version, @n_groups, @n_runs, @standard_error,
                            @excluded (JSON {job id: state} of the batch's jobs that have no result)
    /groups/<gNNN>/         @label (the keys that differ between groups), @spec (JSON, seed removed),
                            @varying (JSON), @n_seeds
        job_ids, seeds      the runs of the group, in batch order
        step, time          record steps and times (s) shared by the runs
        <quantity>/mean, standard_error, values[K][T]   for quantity in QUANTITIES

Pure numpy + h5py; the service (GET /batches/{id}/result, /plot.png) and the CLI read and write it here.
"""

from __future__ import annotations

import json
import math
import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import h5py
import numpy as np

from engine.output.h5md import read_parameters, read_series

#: Per-record quantities of the batch file: name -> (source observable, unit, normalised by its first value).
QUANTITIES = {
    "temperature_translational": ("temperature_translational", "J", False),
    "temperature_rotational": ("temperature_rotational", "J", False),
    "kinetic_energy_translational_ratio": ("kinetic_energy_translational", "", True),
    "sonine_a2_translational": ("sonine_a2_translational", "", False),
    "sonine_a2_rotational": ("sonine_a2_rotational", "", False),
    "sonine_a11": ("sonine_a11", "", False),
}
#: quantities a run file may lack (older files): NaN there instead of an error
OPTIONAL = ("sonine_a2_translational", "sonine_a2_rotational", "sonine_a11")
#: Spec keys that do not define a group: runs differing only in these are seeds of one spec.
NOT_GROUPING = ("seed", "backend")
STANDARD_ERROR = "sample standard deviation over the seeds (ddof = 1) / sqrt(n_seeds); NaN with one seed"


def mean_and_standard_error(values) -> tuple[np.ndarray, np.ndarray]:
    """Mean over axis 0 (the seeds) and its standard error s/sqrt(K) with s the sample deviation (ddof = 1)."""
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 0 or v.shape[0] == 0:
        raise ValueError("mean_and_standard_error needs at least one run (values[K][...], K >= 1)")
    k = v.shape[0]
    mean = v.mean(axis=0)
    if k == 1:
        return mean, np.full_like(mean, np.nan)
    return mean, v.std(axis=0, ddof=1) / math.sqrt(k)


def group_key(spec: dict) -> str:
    """Canonical JSON of a spec without the keys of :data:`NOT_GROUPING`."""
    return json.dumps({k: v for k, v in spec.items() if k not in NOT_GROUPING}, sort_keys=True)


@dataclass
class Run:
    """One run's result file, known by a name (the job id)."""

    name: str
    path: Path


@dataclass
class Group:
    """The runs of one spec (seeds), with their stacked curves and statistics."""

    spec: dict                       # without seed and backend
    runs: list = field(default_factory=list)
    seeds: list = field(default_factory=list)
    step: Optional[np.ndarray] = None
    time: Optional[np.ndarray] = None
    values: dict = field(default_factory=dict)   # quantity -> [K][T]
    mean: dict = field(default_factory=dict)
    standard_error: dict = field(default_factory=dict)
    label: str = ""
    varying: dict = field(default_factory=dict)

    @property
    def n_seeds(self) -> int:
        return len(self.runs)


def aggregate(runs: Sequence[Run]) -> list[Group]:
    """Group runs by spec apart from the seed and compute each group's mean curves and standard errors.

    Groups come in the order of their first run; within a group the runs keep their order. Raises
    ValueError when runs of one group do not share their record steps (they were not made from equal specs).
    """
    groups: dict[str, Group] = {}
    for run in runs:
        spec = read_parameters(run.path)["spec"]
        key = group_key(spec)
        g = groups.get(key)
        if g is None:
            g = groups[key] = Group(spec={k: v for k, v in spec.items() if k not in NOT_GROUPING})
        first = read_series(run.path, "temperature_translational")
        if g.step is None:
            g.step, g.time = first["step"], first["time"]
        elif not np.array_equal(first["step"], g.step):
            raise ValueError(f"run {run.name} has {len(first['step'])} records at other steps than run "
                             f"{g.runs[0]} of the same spec ({len(g.step)} records): the runs cannot be averaged")
        g.runs.append(run.name)
        g.seeds.append(int(spec.get("seed", 0)))
        for name, (source, _, normalised) in QUANTITIES.items():
            if source == "temperature_translational":
                v = np.asarray(first["value"], dtype=np.float64)
            elif name in OPTIONAL and not _has_series(run.path, source):
                v = np.full(len(g.step), np.nan)
            else:
                v = np.asarray(read_series(run.path, source)["value"], dtype=np.float64)
            if normalised:
                v = v / v[0] if v.size and v[0] != 0 else np.full_like(v, np.nan)
            g.values.setdefault(name, []).append(v)
    out = list(groups.values())
    varying = _varying_keys([g.spec for g in out])
    for g in out:
        for name in QUANTITIES:
            g.values[name] = np.vstack(g.values[name])
            g.mean[name], g.standard_error[name] = mean_and_standard_error(g.values[name])
        g.varying = {k: g.spec.get(k) for k in varying}
        g.label = ", ".join(f"{k}={_fmt(g.spec.get(k))}" for k in varying) or \
            ", ".join(f"{k}={_fmt(g.spec.get(k))}" for k in ("shape", "n_particles", "e_n", "e_t"))
    return out


def write_batch_result(path, groups: Sequence[Group], *, batch_id: str = "",
                       excluded: Optional[dict] = None) -> Path:
    """Write the batch file (layout in the module docstring) through a temporary name and a rename."""
    from engine.version import __version__

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex}.part")  # concurrent writers never share it
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["batch_id"] = batch_id
            f.attrs["creator"] = "demq"
            f.attrs["creator_version"] = __version__
            f.attrs["n_groups"] = len(groups)
            f.attrs["n_runs"] = sum(g.n_seeds for g in groups)
            f.attrs["standard_error"] = STANDARD_ERROR
            f.attrs["excluded"] = json.dumps(excluded or {}, sort_keys=True)
            root = f.create_group("groups")
            for i, g in enumerate(groups):
                h = root.create_group(f"g{i:03d}")
                h.attrs["label"] = g.label
                h.attrs["spec"] = json.dumps(g.spec, sort_keys=True)
                h.attrs["varying"] = json.dumps(g.varying, sort_keys=True)
                h.attrs["n_seeds"] = g.n_seeds
                h.create_dataset("job_ids", data=np.array(g.runs, dtype=h5py.string_dtype()))
                h.create_dataset("seeds", data=np.asarray(g.seeds, dtype=np.int64))
                h.create_dataset("step", data=np.asarray(g.step, dtype=np.int64))
                h.create_dataset("time", data=np.asarray(g.time, dtype=np.float64)).attrs["unit"] = "s"
                for name, (_, unit, _) in QUANTITIES.items():
                    q = h.create_group(name)
                    for part, data in (("mean", g.mean[name]), ("standard_error", g.standard_error[name]),
                                       ("values", g.values[name])):
                        ds = q.create_dataset(part, data=data)
                        if unit:
                            ds.attrs["unit"] = unit
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def read_batch_result(path) -> dict:
    """The batch file as plain data: attributes and, per group, its arrays ({quantity: {mean, ...}})."""
    with h5py.File(path, "r") as f:
        out = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        out["excluded"] = json.loads(out.get("excluded", "{}"))
        groups = []
        for name in sorted(f["groups"]):
            h = f["groups"][name]
            g = {"name": name, "label": h.attrs["label"], "spec": json.loads(h.attrs["spec"]),
                 "varying": json.loads(h.attrs["varying"]), "n_seeds": int(h.attrs["n_seeds"]),
                 "job_ids": [x.decode() if isinstance(x, bytes) else str(x) for x in h["job_ids"][()]],
                 "seeds": h["seeds"][()], "step": h["step"][()], "time": h["time"][()]}
            for q in QUANTITIES:
                if q in h:  # older batch files lack the Sonine cumulants
                    g[q] = {part: h[q][part][()] for part in ("mean", "standard_error", "values")}
            groups.append(g)
        out["groups"] = groups
    return out


def _has_series(path, name: str) -> bool:
    with h5py.File(path, "r") as f:
        return name in f["observables"]


def _varying_keys(specs: Sequence[dict]) -> list:
    if len(specs) < 2:
        return []
    keys = sorted(set().union(*specs))
    return [k for k in keys if len({json.dumps(s.get(k)) for s in specs}) > 1]


def _fmt(v) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)
