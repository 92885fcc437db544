"""XDMF sidecar of a result file, so ParaView and VisIt open the particles directly (neither reads H5MD).

``write_xdmf("run.h5")`` writes ``run.xmf`` next to it. The sidecar holds no data: every array is a
HyperSlab into the HDF5 file, which it names by its relative file name (keep the two files together).

Layout (XDMF 3)::

    Domain
      Grid "particles"  CollectionType=Temporal, one Uniform grid per snapshot frame k:
        Time            the frame's time (s)
        Topology        Polyvertex, N points
        Geometry        XYZ  <- /particles/all/position/value[k]        (m, in the box [0, L)^3)
        Attributes      velocity (Vector, m/s), angular_velocity (Vector, 1/s, space frame),
                        orientation (a 4-component Vector: quaternion w, x, y, z, body -> space),
                        radius (Scalar, m) or semi_axes (Vector a, b, c in m along the body axes),
                        species, id (Scalar), mass (Scalar, kg)
      Grid "box"        the periodic box as one Hexahedron (its 8 corners inline, m), with
                        Information elements "edges" and "boundary"

In ParaView: open the .xmf with the "XDMF Reader" (Xdmf3), then a Glyph filter (sphere, scale by radius).
A result without snapshots gets no sidecar (:func:`write_xdmf` returns None).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional
from xml.sax.saxutils import quoteattr

import h5py
import numpy as np

PART = "/particles/all"
#: time-dependent elements -> (XDMF attribute name, AttributeType)
FRAME_ELEMENTS = (("velocity", "Vector"), ("angular_velocity", "Vector"), ("orientation", "Vector"))
#: fixed per-particle datasets -> AttributeType
FIXED = (("radius", "Scalar"), ("semi_axes", "Vector"), ("species", "Scalar"), ("id", "Scalar"),
         ("mass", "Scalar"))


def sidecar_path(h5_path) -> Path:
    """``result.h5`` -> ``result.xmf``."""
    return Path(h5_path).with_suffix(".xmf")


def _number(ds: h5py.Dataset) -> tuple[str, int]:
    kind = ds.dtype.kind
    return ("Float" if kind == "f" else "UInt" if kind == "u" else "Int"), ds.dtype.itemsize


def _item(ds: h5py.Dataset, h5_ref: str, dims: tuple) -> str:
    nt, prec = _number(ds)
    d = " ".join(str(x) for x in dims)
    return (f'<DataItem Dimensions="{d}" NumberType="{nt}" Precision="{prec}" Format="HDF">'
            f'{h5_ref}:{ds.name}</DataItem>')


def _slab(ds: h5py.Dataset, h5_ref: str, k: int) -> str:
    """Frame ``k`` of a ``value[T][N][D]`` dataset, as an XDMF HyperSlab of shape (N, D)."""
    _, n, d = ds.shape
    return (f'<DataItem ItemType="HyperSlab" Dimensions="{n} {d}" Type="HyperSlab">'
            f'<DataItem Dimensions="3 3" Format="XML">{k} 0 0  1 1 1  1 {n} {d}</DataItem>'
            f'{_item(ds, h5_ref, ds.shape)}</DataItem>')


def xdmf_text(h5_path, h5_ref: Optional[str] = None, *, f: Optional[h5py.File] = None) -> Optional[str]:
    """The XDMF document for a finished result file, or None when it holds no snapshot.

    ``h5_ref`` is the file name written into the document (default: the result's own base name, so the
    sidecar works next to it); the service passes its download name instead. ``f``: the result, already open
    (the writer's own handle before it closes the file; it is left open), else ``h5_path`` is opened.
    """
    h5_path = Path(h5_path)
    if f is None:
        with h5py.File(h5_path, "r") as opened:
            return xdmf_text(h5_path, h5_ref, f=opened)
    ref = quoteattr(h5_ref or h5_path.name)[1:-1]
    part = f.get(PART)
    if part is None or "position" not in part or part["position/value"].shape[0] == 0:
        return None
    pos = part["position/value"]
    n_frames, n = pos.shape[0], pos.shape[1]
    times = part["position/time"][()]
    steps = part["position/step"][()]
    edges = part["box/edges"][()].astype(float)
    fixed = [(name, kind, part[name]) for name, kind in FIXED if name in part]
    frames = [(name, kind, part[f"{name}/value"]) for name, kind in FRAME_ELEMENTS
              if name in part and part[f"{name}/value"].shape[0] == n_frames]
    lines = ['<?xml version="1.0" ?>', '<!DOCTYPE Xdmf SYSTEM "Xdmf.dtd" []>',
             '<Xdmf Version="3.0" xmlns:xi="http://www.w3.org/2001/XInclude">', "<Domain>",
             '<Grid Name="particles" GridType="Collection" CollectionType="Temporal">']
    for k in range(n_frames):
        lines.append(f'<Grid Name="frame {k} step {int(steps[k])}" GridType="Uniform">')
        lines.append(f'<Time Value="{float(times[k])!r}"/>')
        lines.append(f'<Topology TopologyType="Polyvertex" NumberOfElements="{n}" NodesPerElement="1"/>')
        lines.append(f'<Geometry GeometryType="XYZ">{_slab(pos, ref, k)}</Geometry>')
        for name, kind, ds in frames:
            lines.append(f'<Attribute Name="{name}" AttributeType="{kind}" Center="Node">'
                         f'{_slab(ds, ref, k)}</Attribute>')
        for name, kind, ds in fixed:
            lines.append(f'<Attribute Name="{name}" AttributeType="{kind}" Center="Node">'
                         f'{_item(ds, ref, ds.shape)}</Attribute>')
        lines.append("</Grid>")
    lines.append("</Grid>")
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float) * edges
    corners = corners[[0, 1, 3, 2, 4, 5, 7, 6]]      # VTK hexahedron order
    lines += ['<Grid Name="box" GridType="Uniform">',
              f'<Information Name="edges" Value="{" ".join(repr(float(e)) for e in edges)}"/>',
              '<Information Name="boundary" Value="periodic periodic periodic"/>',
              '<Topology TopologyType="Hexahedron" NumberOfElements="1">'
              '<DataItem Dimensions="1 8" NumberType="Int" Format="XML">0 1 2 3 4 5 6 7</DataItem></Topology>',
              '<Geometry GeometryType="XYZ"><DataItem Dimensions="8 3" NumberType="Float" Precision="8" '
              'Format="XML">' + " ".join(repr(float(c)) for c in corners.ravel()) + "</DataItem></Geometry>",
              "</Grid>", "</Domain>", "</Xdmf>", ""]
    return "\n".join(lines)


def write_xdmf(h5_path, text: Optional[str] = None) -> Optional[Path]:
    """Write ``<stem>.xmf`` next to the finished result ``h5_path`` (atomically); None without snapshots.
    ``text``: its :func:`xdmf_text`, when the caller has it (else it is read from the file)."""
    text = xdmf_text(h5_path) if text is None else text
    if text is None:
        return None
    out = sidecar_path(h5_path)
    tmp = out.with_name(out.name + ".part")
    tmp.write_text(text)
    os.replace(tmp, out)
    return out
