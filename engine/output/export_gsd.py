"""Export a result's snapshot frames to GSD (HOOMD-blue's format, read by OVITO, freud, HOOMD).

One GSD frame per H5MD snapshot frame, in SI units (GSD itself is unit-free: lengths in m, masses in kg,
time in s, so velocities in m/s and angular momenta in kg m^2/s):

- ``configuration/box`` = [L, L, L, 0, 0, 0]; ``configuration/step`` = the engine's cooling-run step.
- ``particles/position``: GSD's box is centred at the origin, ours spans [0, L): x_gsd = (x mod L) - L/2.
- ``particles/orientation``: both our H5MD ``dem`` module and the HOOMD schema store the quaternion
  scalar first (w, x, y, z), rotating body into space frame, so it is copied as it is (OVITO's own
  Orientation property is x, y, z, w; its GSD reader does that reordering).
- ``particles/velocity`` (m/s), ``particles/mass`` (kg), ``particles/moment_inertia`` (principal
  moments about the body axes, kg m^2: m/5 (b^2 + c^2, a^2 + c^2, a^2 + b^2) from the semi-axes; 2/5 m r^2
  for spheres).
- ``particles/angmom``: HOOMD's quaternion-form angular momentum P = 2 q (x) (0, S) with
  S = I_body . omega_body the angular momentum in the body frame and omega_body = R(q)^T omega_space
  (hoomd-blue's "Quaternions for angular momentum", Kamberaj 2005); S = 1/2 Im(q* (x) P) recovers it.
- Spheres: ``particles/diameter`` = 2 r, one type per species ("A", "B", ...), ``type_shapes`` Sphere
  with the species diameter. Ellipsoids: one type "E" per distinct shape, ``type_shapes`` Ellipsoid with a, b, c (the
  semi-axes along body x, y, z), ``diameter`` = 2 a (the bounding sphere).
"""

from __future__ import annotations

import os
import string
from pathlib import Path

import h5py
import numpy as np

PART = "particles/all"


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions, scalar first."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([pw * qw - px * qx - py * qy - pz * qz,
                     pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx,
                     pw * qz + px * qy - py * qx + pz * qw], axis=-1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """q v q* for unit quaternions q (..., 4) and vectors v (..., 3)."""
    v4 = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1)
    return quat_mul(quat_mul(q, v4), quat_conj(q))[..., 1:]


def body_inertia(mass: np.ndarray, semi_axes: np.ndarray) -> np.ndarray:
    """Principal moments (N, 3) in kg m^2 of solid ellipsoids with semi-axes (N, 3) along body x, y, z."""
    a2 = np.asarray(semi_axes, dtype=float) ** 2
    return np.asarray(mass, dtype=float)[:, None] / 5.0 * np.stack(
        [a2[:, 1] + a2[:, 2], a2[:, 0] + a2[:, 2], a2[:, 0] + a2[:, 1]], axis=1)


def angmom_quaternion(q: np.ndarray, omega_space: np.ndarray, inertia: np.ndarray) -> np.ndarray:
    """HOOMD's P = 2 q (x) (0, I omega_body), omega_body = R(q)^T omega_space (kg m^2/s)."""
    omega_body = rotate(quat_conj(q), omega_space)
    s4 = np.concatenate([np.zeros(q.shape[:-1] + (1,)), inertia * omega_body], axis=-1)
    return 2.0 * quat_mul(q, s4)


def _type_names(k: int) -> list[str]:
    return [string.ascii_uppercase[i] if i < 26 else f"T{i}" for i in range(k)]


def _create_for_gsd(path: Path) -> None:
    """Create ``path`` empty with mode 0666 less the umask, as HDF5 creates the results (0644 under the usual
    umask 022): libgsd creates its files 0640, and keeps the mode of a file that exists when it opens it (a
    leftover of an interrupted export is removed first, as its mode could be any)."""
    path.unlink(missing_ok=True)
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666))


def export_gsd(h5_path, out_path) -> Path:
    """Write every snapshot frame of the result ``h5_path`` to the GSD file ``out_path`` (atomically; its mode is
    that of the results: 0666 less the umask)."""
    import gsd.hoomd

    out_path = Path(out_path)
    with h5py.File(h5_path, "r") as f:
        part = f.get(PART)
        if part is None or "position" not in part or part["position/value"].shape[0] == 0:
            raise ValueError(f"{h5_path}: the result holds no snapshot frame (spec snapshots = 0): nothing to export")
        edges = part["box/edges"][()].astype(float)
        n = part["position/value"].shape[1]
        mass = part["mass"][()] if "mass" in part else np.ones(n)
        species = part["species"][()].astype(np.int64) if "species" in part else np.zeros(n, np.int64)
        if "semi_axes" in part:
            axes = part["semi_axes"][()].astype(float)
        else:
            axes = np.repeat(part["radius"][()].astype(float)[:, None], 3, axis=1)
        ellipsoid = "semi_axes" in part
        inertia = body_inertia(mass, axes)
        if ellipsoid:                                  # one type per distinct shape
            unique, typeid = np.unique(axes, axis=0, return_inverse=True)
            types = [f"E{i}" if len(unique) > 1 else "E" for i in range(len(unique))]
            shapes = [{"type": "Ellipsoid", "a": float(a), "b": float(b), "c": float(c)} for a, b, c in unique]
            diameter = 2.0 * axes.max(axis=1)
        else:
            n_types = int(species.max()) + 1 if n else 1
            types, typeid = _type_names(n_types), species
            diameter = 2.0 * axes[:, 0]
            shapes = [{"type": "Sphere", "diameter": float(diameter[species == t][0]) if np.any(species == t)
                       else 0.0} for t in range(n_types)]
        frames = part["position/value"].shape[0]
        steps = part["position/step"][()]

        def series(name, k, default):
            g = part.get(name)
            return g["value"][k].astype(float) if g is not None and g["value"].shape[0] > k else default

        tmp = out_path.with_name(out_path.name + ".part")
        _create_for_gsd(tmp)
        with gsd.hoomd.open(tmp, "w") as traj:
            for k in range(frames):
                pos = np.mod(part["position/value"][k].astype(float), edges) - edges / 2.0
                q = series("orientation", k, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))
                omega = series("angular_velocity", k, np.zeros((n, 3)))
                fr = gsd.hoomd.Frame()
                fr.configuration.step = int(steps[k])
                fr.configuration.dimensions = 3
                fr.configuration.box = [float(edges[0]), float(edges[1]), float(edges[2]), 0.0, 0.0, 0.0]
                p = fr.particles
                p.N = n
                p.types = types
                p.typeid = typeid.astype(np.uint32)
                p.type_shapes = shapes
                p.position = pos.astype(np.float32)
                p.orientation = q.astype(np.float32)
                p.velocity = series("velocity", k, np.zeros((n, 3))).astype(np.float32)
                p.angmom = angmom_quaternion(q, omega, inertia).astype(np.float32)
                p.mass = np.asarray(mass, dtype=np.float32)
                p.moment_inertia = inertia.astype(np.float32)
                p.diameter = diameter.astype(np.float32)
                traj.append(fr)
    os.replace(tmp, out_path)
    return out_path

