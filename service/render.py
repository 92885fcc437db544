"""A picture of one snapshot frame: spheres or oriented spheroids, coloured by speed or |omega|, with a colour
bar and the periodic box outline.

Two renderers give the same picture (same view direction, colour map and scale):

- ``ovito``: OVITO's Tachyon ray tracer (shaded 3-D particles), used when the ``ovito`` module imports and
  can render (it needs a Vulkan loader: Debian's ``libvulkan1`` + ``mesa-vulkan-drivers``);
- ``matplotlib``: an orthographic projection. The silhouette of a sphere is a circle of its radius, that of
  an ellipsoid with covariance S = R diag(a^2, b^2, c^2) R^T the ellipse y^T (S_yy)^-1 y = 1 of S's
  screen block (exact for a parallel projection); particles are drawn back to front.

``auto`` tries OVITO and falls back to matplotlib. Units: positions in m, speed in m/s, |omega| in 1/s.
"""

from __future__ import annotations

import io
import logging
import math
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

log = logging.getLogger("demq.render")

#: what a frame may be coloured by -> (label of the colour bar)
COLOURS = {"speed": "speed |v| (m/s)", "omega": "angular speed |ω| (1/s)"}
AZIMUTH, ELEVATION = math.radians(-58.0), math.radians(24.0)
_OVITO_LOCK = threading.Lock()       # OVITO has one global scene per process
_ROOT = str(Path(__file__).resolve().parents[1])


class NoSnapshot(LookupError):
    """The result holds no snapshot frame."""


class FrameOutOfRange(IndexError):
    """The frame index is outside the result's frames."""


@dataclass
class Frame:
    index: int
    n_frames: int
    step: int
    time: float                # s
    edges: np.ndarray          # (3,) m
    position: np.ndarray       # (N, 3) m, in [0, L)
    orientation: np.ndarray    # (N, 4) w, x, y, z, body -> space
    axes: np.ndarray           # (N, 3) semi-axes in m (a = b = c = radius for spheres)
    ellipsoid: bool
    value: np.ndarray          # (N,) the colour quantity
    label: str


def frame_count(path) -> int:
    with h5py.File(path, "r") as f:
        part = f.get("particles/all")
        return 0 if part is None or "position" not in part else int(part["position/value"].shape[0])


def read_frame(path, frame: int = -1, colour: str = "speed") -> Frame:
    """Frame ``frame`` (Python indexing: -1 = last) of a result; raises NoSnapshot / FrameOutOfRange."""
    with h5py.File(path, "r") as f:
        part = f.get("particles/all")
        if part is None or "position" not in part or part["position/value"].shape[0] == 0:
            raise NoSnapshot("the result holds no snapshot frame (spec snapshots = 0, or not an engine result)")
        t = part["position/value"].shape[0]
        if not -t <= frame < t:
            raise FrameOutOfRange(f"frame {frame} is out of range: the result has {t} snapshot frames "
                                  f"(0 ... {t - 1}, or -{t} ... -1 from the end)")
        k = frame % t
        n = part["position/value"].shape[1]
        ellipsoid = "semi_axes" in part
        axes = part["semi_axes"][()] if ellipsoid else np.repeat(part["radius"][()][:, None], 3, axis=1)
        q = part["orientation/value"][k] if "orientation" in part else np.tile([1.0, 0, 0, 0], (n, 1))
        source = "velocity" if colour == "speed" else "angular_velocity"
        vec = part[f"{source}/value"][k] if source in part else np.zeros((n, 3))
        return Frame(index=k, n_frames=t, step=int(part["position/step"][k]), time=float(part["position/time"][k]),
                     edges=part["box/edges"][()].astype(float), position=part["position/value"][k].astype(float),
                     orientation=np.asarray(q, dtype=float), axes=np.asarray(axes, dtype=float), ellipsoid=ellipsoid,
                     value=np.linalg.norm(np.asarray(vec, dtype=float), axis=1), label=COLOURS[colour])


def _view() -> tuple[np.ndarray, np.ndarray]:
    """Rows (screen right, screen up, towards the viewer) of the view rotation, and the camera direction."""
    d = np.array([math.cos(ELEVATION) * math.cos(AZIMUTH), math.cos(ELEVATION) * math.sin(AZIMUTH),
                  math.sin(ELEVATION)])
    right = np.array([-math.sin(AZIMUTH), math.cos(AZIMUTH), 0.0])
    return np.stack([right, np.cross(d, right), d]), -d


def _rotation_matrices(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def _title(fr: Frame, path_label: str) -> str:
    shape = "spheroids" if fr.ellipsoid else "spheres"
    return f"{path_label}N = {len(fr.position)} {shape}, frame {fr.index}/{fr.n_frames - 1}, t = {fr.time:.4g} s"


def render_matplotlib(fr: Frame, title: str = "", size=(6.4, 5.6), dpi: int = 100) -> bytes:
    """PNG of the frame as an orthographic projection (see the module docstring). Needs the ``plots`` extra
    (engine.optional.MissingExtra without it)."""
    from engine.optional import require

    require("matplotlib", "plots", "the snapshot picture (renderer=matplotlib, or auto without OVITO)")
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import EllipseCollection, LineCollection
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    view, _ = _view()
    centre = fr.edges / 2.0
    xyz = (fr.position - centre) @ view.T
    rot = view @ _rotation_matrices(fr.orientation)                      # body -> screen
    cov = np.einsum("nij,nj,nkj->nik", rot[:, :2, :], fr.axes ** 2, rot[:, :2, :])
    evals, evecs = np.linalg.eigh(cov)                                    # ascending
    major = np.sqrt(np.maximum(evals[:, 1], 0.0))
    minor = np.sqrt(np.maximum(evals[:, 0], 0.0))
    angle = np.degrees(np.arctan2(evecs[:, 1, 1], evecs[:, 0, 1]))
    order = np.argsort(xyz[:, 2])                                         # far first
    vmax = float(fr.value.max()) if fr.value.size and fr.value.max() > 0 else 1.0
    norm, cmap = Normalize(0.0, vmax), colormaps["viridis"]

    fig = Figure(figsize=size, dpi=dpi)
    ax = fig.add_subplot()
    corners = (np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]) * fr.edges - centre) @ view.T
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    depth_mid = np.array([(corners[i, 2] + corners[j, 2]) / 2 for i, j in edges])
    back = [corners[[i, j], :2] for (i, j), d in zip(edges, depth_mid) if d < 0]
    front = [corners[[i, j], :2] for (i, j), d in zip(edges, depth_mid) if d >= 0]
    ax.add_collection(LineCollection(back, colors="0.55", linewidths=0.8, zorder=1))
    ax.add_collection(EllipseCollection(2 * major[order], 2 * minor[order], angle[order], units="xy",
                                        offsets=xyz[order, :2], offset_transform=ax.transData,
                                        facecolors=cmap(norm(fr.value[order])), edgecolors="0.15",
                                        linewidths=0.25, zorder=2))
    ax.add_collection(LineCollection(front, colors="0.15", linewidths=1.0, zorder=3))
    half = 0.5 * float(np.ptp(corners[:, :2], axis=0).max()) * 1.04
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)
    fig.colorbar(ScalarMappable(norm, cmap), ax=ax, label=fr.label, shrink=0.8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def ovito_available() -> bool:
    try:
        import ovito.vis  # noqa: F401
    except Exception:
        return False
    import ctypes.util

    return ctypes.util.find_library("vulkan") is not None


def offered_renderers() -> list[str]:
    """The ``renderer`` values this host serves, in the order of the OpenAPI enum: 'auto', 'ovito' where OVITO can
    render (:func:`ovito_available`), 'matplotlib' (without the plots extra it answers 501 naming the extra, as
    every figure route does)."""
    return ["auto", *(["ovito"] if ovito_available() else []), "matplotlib"]


def render_ovito(fr: Frame, title: str = "", size=(640, 560)) -> bytes:
    """PNG of the frame rendered by OVITO's Tachyon ray tracer, with a colour legend and the cell."""
    from ovito.data import DataCollection
    from ovito.modifiers import ColorCodingModifier
    from ovito.pipeline import Pipeline, StaticSource
    from ovito.vis import ColorLegendOverlay, TachyonRenderer, TextLabelOverlay, Viewport

    data = DataCollection()
    cell = np.zeros((3, 4))
    cell[:, :3] = np.diag(fr.edges)
    data.create_cell(cell, pbc=(True, True, True))
    p = data.create_particles(count=len(fr.position))
    p.create_property("Position", data=fr.position)
    if fr.ellipsoid:
        p.create_property("Aspherical Shape", data=fr.axes)
        p.create_property("Orientation", data=fr.orientation[:, [1, 2, 3, 0]])   # OVITO: x, y, z, w
    else:
        p.create_property("Radius", data=fr.axes[:, 0])
    p.create_property("Colour value", data=fr.value)
    vmax = float(fr.value.max()) if fr.value.size and fr.value.max() > 0 else 1.0
    coding = ColorCodingModifier(property="Colour value", gradient=ColorCodingModifier.Viridis(),
                                 auto_adjust_range=False, start_value=0.0, end_value=vmax)
    pipeline = Pipeline(source=StaticSource(data=data))
    pipeline.modifiers.append(coding)
    _, camera = _view()
    with _OVITO_LOCK:
        pipeline.add_to_scene()
        try:
            vp = Viewport(type=Viewport.Type.Ortho, camera_dir=tuple(camera))
            vp.zoom_all(size=size)
            vp.overlays.append(ColorLegendOverlay(modifier=coding, title=fr.label, alignment=0x0002 | 0x0080,
                                                  orientation=0x2, legend_size=0.45, font_size=0.05, offset_x=-0.06))
            vp.overlays.append(TextLabelOverlay(text=title, font_size=0.035, alignment=0x0001 | 0x0020))
            with tempfile.TemporaryDirectory() as tmp:
                png = Path(tmp) / "frame.png"
                vp.render_image(size=size, filename=str(png), background=(1, 1, 1),
                                renderer=TachyonRenderer(antialiasing_samples=2, ambient_occlusion=False,
                                                         shadows=False))
                return png.read_bytes()
        finally:
            pipeline.remove_from_scene()


def render_ovito_isolated(path, frame: int, colour: str, title: str, timeout: float = 60.0) -> bytes:
    """:func:`render_ovito` in a child process: OVITO's Qt core renders only from its process's main thread
    (a server answers in worker threads), and a crash of the renderer must not take the server down."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "frame.png"
        proc = subprocess.run([sys.executable, "-m", "service.render", str(path), str(frame), colour, title, str(out)],
                              capture_output=True, text=True, timeout=timeout, cwd=_ROOT)
        if proc.returncode != 0 or not out.is_file():
            raise RuntimeError(f"OVITO rendering failed (exit {proc.returncode}): {proc.stderr[-2000:]}")
        return out.read_bytes()


def snapshot_png(path, frame: int = -1, colour: str = "speed", renderer: str = "auto", label: str = "") -> bytes:
    """PNG of one snapshot frame of the result ``path``; ``renderer`` is auto | ovito | matplotlib.

    Raises NoSnapshot / FrameOutOfRange before any rendering starts."""
    fr = read_frame(path, frame, colour)
    title = _title(fr, label)
    if renderer == "ovito" or (renderer == "auto" and ovito_available()):
        try:
            return render_ovito_isolated(path, frame, colour, title)
        except Exception:
            if renderer == "ovito":
                raise
            log.exception("OVITO rendering failed; falling back to matplotlib")
    return render_matplotlib(fr, title)


if __name__ == "__main__":        # python -m service.render RESULT.h5 FRAME COLOUR TITLE OUT.png (OVITO)
    _path, _frame, _colour, _title_text, _out = sys.argv[1:6]
    Path(_out).write_bytes(render_ovito(read_frame(_path, int(_frame), _colour), _title_text))
