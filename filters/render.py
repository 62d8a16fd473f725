"""Off-screen PNG rendering of RGBA volumes with pyvista (the ``io`` extra).

The volume is shown as it is: each voxel's RGB is its colour and its A (through a linear
opacity ramp over 0-255) its opacity per ``opacity_unit_distance``; no colour map is applied.

Off-screen rendering works without an X server: the VTK wheel then renders through EGL
(Mesa's software rasteriser where there is no GPU), which needs the system libraries that
``scripts/setup.sh`` installs.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np
import pyvista as pv

from nebula_rt.pipeline.outputs import Publication

from .image_data import to_vtk_order
from .vti import ArrayNotFoundError, read_vti

__all__ = ["render_png_from_vti", "render_rgba_png"]


def _prefer_egl_without_display() -> None:
    """Without an X display, make VTK go straight to EGL.

    The VTK wheel's render-window factory tries X11 first and logs "bad X
    server connection" before falling back to EGL; with no ``DISPLAY`` that
    attempt is pointless. Only done when Mesa/GLVND's ``libEGL`` is present
    (otherwise VTK is left to its own fallback, OSMesa) and when the user has
    not chosen a window class through ``VTK_DEFAULT_OPENGL_WINDOW``.
    """
    if os.environ.get("DISPLAY") or os.environ.get("VTK_DEFAULT_OPENGL_WINDOW"):
        return
    import ctypes.util

    if ctypes.util.find_library("EGL"):
        os.environ["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"


def _write_bytes_atomic(path: Path, data: bytes) -> None:
    # a temporary file unique to this call, renamed onto the target once complete
    with Publication() as pub:
        tmp = pub.stage(path)
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        pub.publish()


def render_rgba_png(
    path: str | os.PathLike,
    rgba: np.ndarray,
    spacing: tuple[float, float, float],
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    window_size: tuple[int, int] = (800, 800),
    background: Any = "black",
    azimuth: float = 30.0,
    elevation: float = 20.0,
) -> Path:
    """Volume-render a ``uint8`` RGBA grid off screen and save it as a PNG.

    Parameters
    ----------
    path : path-like
        PNG file to write (atomically: temporary file, then rename).
    rgba : numpy.ndarray
        ``uint8`` array of shape ``(nx, ny, nz, 4)`` indexed ``[x, y, z, channel]``.
    spacing : tuple of 3 floats
        Voxel size along x, y, z.
    origin : tuple of 3 floats
        Centre of voxel ``[0, 0, 0]``.
    window_size : tuple of 2 ints
        Image width and height in pixels.
    background : color-like
        Background colour (any colour PyVista accepts).
    azimuth, elevation : float
        Camera rotation in degrees, applied to the view looking down the
        z axis (x to the right, y up).

    Returns
    -------
    pathlib.Path
        The PNG written.
    """
    _prefer_egl_without_display()  # read when the render window is made
    path = Path(os.fspath(path))
    rgba = np.asarray(rgba)
    if rgba.ndim != 4 or rgba.shape[3] != 4:
        raise ValueError(f"rgba must have shape (nx, ny, nz, 4), got {rgba.shape}")
    if rgba.dtype != np.uint8:
        raise TypeError(f"rgba must be uint8, got {rgba.dtype}")
    if min(rgba.shape[:3]) < 2:
        raise ValueError(f"rgba needs at least 2 voxels along each axis to render, got {rgba.shape}")
    spacing = tuple(float(s) for s in spacing)
    origin = tuple(float(o) for o in origin)
    if len(spacing) != 3 or min(spacing) <= 0:
        raise ValueError(f"spacing must be 3 positive numbers, got {spacing}")
    width, height = (int(n) for n in window_size)
    if not path.parent.is_dir():
        raise FileNotFoundError(
            2, f"cannot write {path}: directory {path.parent} does not exist", str(path)
        )

    nx, ny, nz = rgba.shape[:3]
    # Render in units of the smallest voxel edge: with dependent RGBA components VTK's GPU
    # mapper corrects the alpha channel's opacity with the ScalarOpacityUnitDistance of
    # component 3, which add_volume leaves at 1.0 (it sets component 0's): alpha acts as the
    # opacity per 1.0 world unit (measured with VTK 9.7: a 32^3 box of alpha 20/255 at
    # spacing 1/32 rendered as one voxel's opacity). Scaling the geometry so one voxel edge is
    # one unit makes alpha the opacity of one voxel, as the output contract defines it. The
    # picture does not change otherwise: the camera is reset onto the volume.
    unit = min(spacing)
    spacing = tuple(s / unit for s in spacing)
    origin = tuple(o / unit for o in origin)
    img = pv.ImageData(dimensions=(nx, ny, nz), spacing=spacing, origin=origin)
    img.point_data["rgba"] = to_vtk_order("rgba", rgba)

    plotter = pv.Plotter(off_screen=True, window_size=[width, height])
    try:
        plotter.set_background(background)
        # 2-D uint8 scalars with 4 components are shown directly as RGBA
        # (PyVista sets independent_components=False and a linear opacity ramp).
        # The GPU ray caster itself (what "smart" picks where OpenGL works): its opacity
        # table must span the opacity function's own range 0..255 (NATIVE). With the default
        # (SCALAR) it is sampled over the data's alpha range but looked up at alpha/255, so
        # any alpha range other than 0..255 scales every opacity down (a 10-voxel slab of
        # alpha 30 in an empty box rendered 26 of 143).
        actor = plotter.add_volume(
            img,
            scalars="rgba",
            clim=[0, 255],
            mapper="gpu",
            opacity_unit_distance=1.0,
            show_scalar_bar=False,
        )
        actor.GetProperty().SetInterpolationTypeToLinear()  # as ParaView does (VTK's default: nearest)
        mapper = actor.GetMapper()
        mapper.SetScalarOpacityRangeType(mapper.NATIVE)
        mapper.SetColorRangeType(mapper.NATIVE)
        # Sample every half voxel (the mapper's default of 1.0 world unit with automatic
        # adjustment off would skip detail); opacity is corrected to the step by VTK.
        mapper.SetAutoAdjustSampleDistances(False)
        mapper.SetSampleDistance(0.5)
        plotter.view_xy()
        camera = plotter.camera
        camera.Azimuth(float(azimuth))
        camera.Elevation(float(elevation))
        camera.OrthogonalizeViewUp()
        plotter.reset_camera()
        buf = io.BytesIO()
        plotter.screenshot(buf)
    finally:
        plotter.close()
    _write_bytes_atomic(path, buf.getvalue())
    return path


def render_png_from_vti(
    vti_path: str | os.PathLike,
    png_path: str | os.PathLike,
    array_name: str = "rgba",
    **kw: Any,
) -> Path:
    """Render the RGBA point array of a ``.vti`` file to a PNG.

    ``spacing`` and ``origin`` come from the file; other keyword arguments go
    to :func:`render_rgba_png`.
    """
    point_arrays, _fd, spacing, origin, _dims = read_vti(vti_path)
    if array_name not in point_arrays:
        raise ArrayNotFoundError(Path(os.fspath(vti_path)), array_name, sorted(point_arrays))
    kw.setdefault("spacing", spacing)
    kw.setdefault("origin", origin)
    return render_rgba_png(png_path, point_arrays[array_name], **kw)
