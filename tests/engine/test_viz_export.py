"""Visualisation outputs of real (tiny) engine results: the XDMF sidecar read by VTK's XDMF reader, the GSD
export read by gsd.hoomd and by OVITO (counts, positions, shapes, a Tachyon render), `demq export`."""

from __future__ import annotations

import ctypes.util
import shutil

import h5py
import numpy as np
import pytest

from engine.driver.simulate import run
from engine.output.export_gsd import body_inertia, export_gsd, rotate
from engine.output.xdmf import sidecar_path, xdmf_text

# 64 rough spheres (e_t = 0.5, so they spin) and 64 smooth spheroids xi = 2, three snapshots each
SPHERES = dict(n_particles=64, volume_fraction=0.05, box_length=0.5, t_end=0.1, thermalization=0.5, snapshots=3,
               backend="cpu", velocity_rms=1.0, e_t=0.5)
ELLIPSOIDS = dict(shape="ellipsoid", elongation=2.0, n_particles=64, volume_fraction=0.05, e_n=0.9, e_t=-1.0,
                  t_end=0.01, thermalization=0.1, snapshots=3, backend="cpu", seed=3)


@pytest.fixture(scope="module", params=["sphere", "ellipsoid"])
def result(request, tmp_path_factory):
    spec = SPHERES if request.param == "sphere" else ELLIPSOIDS
    out = tmp_path_factory.mktemp(request.param) / "result.h5"
    run(spec, out)
    with h5py.File(out) as f:
        part = f["particles/all"]
        data = {k: part[f"{k}/value"][()] for k in ("position", "velocity", "orientation", "angular_velocity")}
        data["time"] = part["position/time"][()]
        data["step"] = part["position/step"][()]
        data["edges"] = part["box/edges"][()]
        data["mass"] = part["mass"][()]
        data["axes"] = part["semi_axes"][()] if "semi_axes" in part else np.repeat(part["radius"][()][:, None], 3, 1)
    data["shape"], data["path"] = request.param, out
    assert data["position"].shape == (3, 64, 3)
    return data


def test_every_result_gets_a_sidecar_naming_the_h5_relatively(result):
    xmf = sidecar_path(result["path"])
    assert xmf.name == "result.xmf" and xmf.is_file()
    text = xmf.read_text()
    assert "result.h5:/particles/all/position/value" in text
    assert str(result["path"].parent) not in text          # relative: the pair can be moved together
    # the writer takes the sidecar from its own open handle: the same document as one read from the closed file
    assert text == xdmf_text(result["path"])


def _read_xdmf(path):
    """Every time step of the sidecar through VTK's XDMF reader: [(time, particles grid, box grid)]."""
    xdmf2 = pytest.importorskip("vtkmodules.vtkIOXdmf2", reason="the vtk wheel (pip install '.[viz]')")
    from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline

    reader = xdmf2.vtkXdmfReader()
    reader.SetFileName(str(path))
    reader.UpdateInformation()
    times = reader.GetOutputInformation(0).Get(vtkStreamingDemandDrivenPipeline.TIME_STEPS())
    out = []
    for t in times:
        reader.UpdateTimeStep(t)
        mb = reader.GetOutputDataObject(0)
        blocks = [mb.GetBlock(b) for b in range(mb.GetNumberOfBlocks())]
        out.append((t, blocks[0].NewInstance(), blocks[1].NewInstance()))
        out[-1][1].DeepCopy(blocks[0])
        out[-1][2].DeepCopy(blocks[1])
    return out


@pytest.mark.heavy   # a real reader: the `viz` extra
def test_vtk_xdmf_reader_gives_every_frame(result, tmp_path):
    pytest.importorskip("vtkmodules.vtkIOXdmf2", reason="the vtk wheel (pip install '.[viz]')")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    # move the pair elsewhere: the reference is relative, so it still opens
    h5 = tmp_path / "result.h5"
    shutil.copy(result["path"], h5)
    shutil.copy(sidecar_path(result["path"]), tmp_path / "result.xmf")
    frames = _read_xdmf(tmp_path / "result.xmf")
    assert len(frames) == 3
    for k, (t, grid, box) in enumerate(frames):
        assert t == pytest.approx(result["time"][k], rel=1e-12, abs=1e-15)
        assert grid.GetNumberOfPoints() == 64
        assert np.array_equal(vtk_to_numpy(grid.GetPoints().GetData()), result["position"][k])
        pd = grid.GetPointData()
        for name in ("velocity", "angular_velocity", "orientation"):
            assert np.array_equal(vtk_to_numpy(pd.GetArray(name)), result[name][k]), name
        assert pd.GetArray("orientation").GetNumberOfComponents() == 4
        size = vtk_to_numpy(pd.GetArray("semi_axes" if result["shape"] == "ellipsoid" else "radius"))
        assert np.array_equal(size.reshape(64, -1), result["axes"] if result["shape"] == "ellipsoid"
                              else result["axes"][:, :1])
        assert vtk_to_numpy(pd.GetArray("species")).shape == (64,)
        corners = vtk_to_numpy(box.GetPoints().GetData())
        assert box.GetNumberOfCells() == 1 and np.allclose(corners.max(axis=0), result["edges"])
        assert np.allclose(corners.min(axis=0), 0.0)
    assert not np.array_equal(frames[0][1].GetPoints().GetData(), frames[2][1].GetPoints().GetData())


def _gsd_frames(path):
    import gsd.hoomd

    with gsd.hoomd.open(path, "r") as traj:
        return [traj[k] for k in range(len(traj))]


def test_gsd_export_matches_the_h5(result, tmp_path):
    frames = _gsd_frames(export_gsd(result["path"], tmp_path / "out.gsd"))
    assert len(frames) == 3
    L = result["edges"]
    inertia = body_inertia(result["mass"], result["axes"])
    for k, fr in enumerate(frames):
        p = fr.particles
        assert p.N == 64 and fr.configuration.step == result["step"][k]
        assert np.allclose(fr.configuration.box, [*L, 0, 0, 0])
        # float32 in GSD: 1e-6 relative of the box edge is the rounding, not a physics tolerance
        assert np.allclose(p.position, result["position"][k] - L / 2, atol=1e-6 * L[0], rtol=0)
        assert np.all(np.abs(p.position) <= L / 2)
        assert np.allclose(p.orientation, result["orientation"][k], atol=1e-6)   # both w, x, y, z
        assert np.allclose(p.velocity, result["velocity"][k], rtol=1e-6, atol=1e-7)
        # HOOMD's angmom P = 2 q (x) (0, S): S = I_body omega_body, and rotated to the space frame it is the
        # lab angular momentum R I_body R^T omega (computed here with rotation matrices, not quaternions)
        q = result["orientation"][k].astype(float)
        P = p.angmom.astype(float)
        qc = q * [1, -1, -1, -1]
        S = 0.5 * (qc[:, 0:1] * P[:, 1:] + P[:, 0:1] * qc[:, 1:] + np.cross(qc[:, 1:], P[:, 1:]))   # Im(q* P)/2
        w, x, y, z = q.T
        R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                      np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                      np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
        omega = result["angular_velocity"][k]
        lab = np.einsum("nij,nj,nkj,nk->ni", R, inertia, R, omega)
        assert np.allclose(np.einsum("nij,nj->ni", R, S), lab, rtol=1e-5, atol=1e-6 * np.abs(lab).max())
        assert np.allclose(rotate(q, S), lab, rtol=1e-5, atol=1e-6 * np.abs(lab).max())
        if result["shape"] == "sphere":
            assert np.abs(lab).max() > 0                          # rough spheres do spin
            assert np.allclose(lab, inertia * omega, rtol=1e-12)  # isotropic: L = I omega
            assert p.type_shapes == [{"type": "Sphere", "diameter": pytest.approx(2 * result["axes"][0, 0])}]
            assert np.allclose(p.diameter, 2 * result["axes"][:, 0], rtol=1e-6)
        else:
            a, b, c = result["axes"][0]
            assert p.type_shapes == [{"type": "Ellipsoid", "a": pytest.approx(a), "b": pytest.approx(b),
                                      "c": pytest.approx(c)}]
            assert a == pytest.approx(2 * b)


def test_demq_export_cli(result, tmp_path, capsys):
    from service.cli import build_parser

    out = tmp_path / "cli.gsd"
    args = build_parser().parse_args(["export", str(result["path"]), "--format", "gsd", "-o", str(out)])
    assert args.func(args) == 0 and out.is_file()
    assert len(_gsd_frames(out)) == 3
    args = build_parser().parse_args(["export", str(tmp_path / "missing.h5"), "-o", str(out)])
    assert args.func(args) == 2
    assert "no result file" in capsys.readouterr().err


def test_gsd_export_refuses_a_result_without_snapshots(tmp_path):
    from engine.output.h5md import H5MDWriter

    w = H5MDWriter(tmp_path / "none.h5", n=4, box_length=1.0, spec_json="{}", derived={}, radius=np.full(4, 0.1))
    path = w.finish({})
    assert not sidecar_path(path).exists()                   # nothing to point at: no sidecar
    with pytest.raises(ValueError, match="no snapshot"):
        export_gsd(path, tmp_path / "none.gsd")


def _ovito():
    ovito_io = pytest.importorskip("ovito.io", reason="the ovito wheel (pip install '.[viz]')")
    return ovito_io


@pytest.mark.heavy   # a real reader: the `viz` extra
def test_ovito_reads_the_gsd_export(result, tmp_path):
    ovito_io = _ovito()
    out = export_gsd(result["path"], tmp_path / "ovito.gsd")
    pipeline = ovito_io.import_file(str(out))
    assert pipeline.source.num_frames == 3
    L = result["edges"]
    for k in range(3):
        data = pipeline.compute(k)
        assert data.particles.count == 64
        # OVITO keeps GSD's origin-centred box: its cell origin is -L/2
        assert np.allclose(data.cell[:, 3], -L / 2) and np.allclose(np.diag(data.cell[:, :3]), L)
        assert np.allclose(data.particles.positions, result["position"][k] - L / 2, atol=1e-6 * L[0])
        q = result["orientation"][k]
        assert np.allclose(data.particles["Orientation"], q[:, [1, 2, 3, 0]], atol=1e-6)   # OVITO: x, y, z, w
        if result["shape"] == "ellipsoid":
            assert np.allclose(data.particles["Aspherical Shape"], result["axes"], rtol=1e-6)
        else:
            assert np.allclose(data.particles["Radius"], result["axes"][:, 0], rtol=1e-6)


@pytest.mark.heavy   # a real reader: the `viz` extra
def test_ovito_tachyon_render_of_a_frame(result, tmp_path):
    ovito_io = _ovito()
    if ctypes.util.find_library("vulkan") is None:
        pytest.skip("OVITO's renderers need a Vulkan loader: apt-get install libvulkan1 mesa-vulkan-drivers")
    from ovito.vis import TachyonRenderer, Viewport

    pipeline = ovito_io.import_file(str(export_gsd(result["path"], tmp_path / "r.gsd")))
    pipeline.add_to_scene()
    try:
        vp = Viewport(type=Viewport.Type.Perspective, camera_dir=(-1, -0.6, -0.5))
        vp.zoom_all()
        png = tmp_path / "frame.png"
        vp.render_image(filename=str(png), size=(240, 180), frame=2, renderer=TachyonRenderer())
    finally:
        pipeline.remove_from_scene()
    from matplotlib.image import imread

    img = imread(png)
    assert img.shape[:2] == (180, 240)
    assert img[..., :3].std() > 0.02                            # not a blank picture: particles and the cell
