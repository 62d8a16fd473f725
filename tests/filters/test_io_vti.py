"""Tests of nebula_rt.filters.vti (.vti files) and nebula_rt.filters.render (PNG volume rendering)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("vtkmodules.vtkIOXML")
pytest.importorskip("pyvista")  # the io extra: VTK and pyvista

from nebula_rt.filters.vti import (  # noqa: E402
    ArrayNotFoundError,
    read_density_array,
    read_vti,
    write_vti,
)

NX, NY, NZ = 5, 4, 3
SPACING = (0.5, 0.25, 2.0)
ORIGIN = (-1.0, 0.5, 3.0)
BIG_INT = 2**53 + 12345  # not representable in float64


def _index_grid() -> np.ndarray:
    i, j, k = np.meshgrid(np.arange(NX), np.arange(NY), np.arange(NZ), indexing="ij")
    return (i + 10 * j + 100 * k).astype(np.float32)


def _rgba() -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.integers(0, 256, size=(NX, NY, NZ, 4), dtype=np.uint8)


@pytest.mark.parametrize("compress", [True, False])
def test_round_trip_exact(tmp_path, compress):
    density = _index_grid() + np.float32(0.125)
    rgba = _rgba()
    field = {
        "photons": 1.0e7 + 0.1,
        "seed": BIG_INT,
        "negative": -(2**63),
        "scene": "reflection nebula, σ_s = 0.3",
        "wavelengths_nm": np.array([450.0, 550.0, 650.0]),
        "counts": np.array([2**62 + 1, -5], dtype=np.int64),
        "single": np.array([3.5]),
    }
    path = tmp_path / "grid.vti"
    out = write_vti(path, {"density": density, "rgba": rgba}, field, SPACING, ORIGIN, compress=compress)
    assert out == path and path.is_file()

    arrays, fd, spacing, origin, dims = read_vti(path)
    assert dims == (NX, NY, NZ)
    assert spacing == SPACING
    assert origin == ORIGIN
    assert set(arrays) == {"density", "rgba"}
    assert arrays["density"].dtype == np.float32 and arrays["density"].shape == (NX, NY, NZ)
    assert arrays["rgba"].dtype == np.uint8 and arrays["rgba"].shape == (NX, NY, NZ, 4)
    np.testing.assert_array_equal(arrays["density"], density)
    np.testing.assert_array_equal(arrays["rgba"], rgba)

    assert fd["photons"] == field["photons"] and isinstance(fd["photons"], float)
    assert fd["seed"] == BIG_INT and isinstance(fd["seed"], int)
    assert fd["negative"] == -(2**63)
    assert fd["scene"] == field["scene"]
    assert fd["wavelengths_nm"].dtype == np.float64
    np.testing.assert_array_equal(fd["wavelengths_nm"], field["wavelengths_nm"])
    assert fd["counts"].dtype == np.int64
    np.testing.assert_array_equal(fd["counts"], field["counts"])
    # a one-element array stays an array
    assert isinstance(fd["single"], np.ndarray) and fd["single"].tolist() == [3.5]


def test_vtk_point_order_is_x_fastest(tmp_path):
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLImageDataReader

    a = _index_grid()
    rgba = np.zeros((NX, NY, NZ, 4), np.uint8)
    rgba[..., 0] = np.arange(NX)[:, None, None]
    rgba[..., 1] = np.arange(NY)[None, :, None]
    rgba[..., 2] = np.arange(NZ)[None, None, :]
    rgba[..., 3] = 200
    path = tmp_path / "order.vti"
    write_vti(path, {"a": a, "rgba": rgba}, {}, SPACING, ORIGIN)

    reader = vtkXMLImageDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    img = reader.GetOutput()
    assert img.GetDimensions() == (NX, NY, NZ)
    assert img.GetOrigin() == ORIGIN
    flat = vtk_to_numpy(img.GetPointData().GetArray("a"))
    flat_rgba = vtk_to_numpy(img.GetPointData().GetArray("rgba"))
    assert flat.shape == (NX * NY * NZ,) and flat_rgba.shape == (NX * NY * NZ, 4)
    for i, j, k in [(0, 0, 0), (1, 0, 0), (4, 3, 2), (2, 1, 0), (3, 0, 2), (0, 3, 1)]:
        p = i + NX * (j + NY * k)
        assert flat[p] == i + 10 * j + 100 * k
        assert tuple(flat_rgba[p]) == (i, j, k, 200)
        # the point's position is the voxel centre
        np.testing.assert_allclose(
            img.GetPoint(p), [ORIGIN[0] + i * SPACING[0], ORIGIN[1] + j * SPACING[1], ORIGIN[2] + k * SPACING[2]]
        )


def test_atomic_write_leaves_no_temp_file(tmp_path):
    path = tmp_path / "a.vti"
    write_vti(path, {"a": _index_grid()}, {"n": 1}, SPACING)
    write_vti(path, {"a": _index_grid() * 2}, {"n": 2}, SPACING)  # overwrite
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.vti"]
    arrays, fd, *_ = read_vti(path)
    assert fd["n"] == 2
    np.testing.assert_array_equal(arrays["a"], _index_grid() * 2)


def test_failed_writes_leave_no_file(tmp_path):
    with pytest.raises(OSError):
        write_vti(tmp_path / "missing_dir" / "a.vti", {"a": _index_grid()}, {}, SPACING)
    assert not (tmp_path / "missing_dir").exists()

    with pytest.raises(TypeError, match="dtype object"):
        write_vti(tmp_path / "b.vti", {"a": np.empty((NX, NY, NZ), dtype=object)}, {}, SPACING)
    with pytest.raises(TypeError):
        write_vti(tmp_path / "c.vti", {"a": _index_grid()}, {"bad": object()}, SPACING)
    with pytest.raises(ValueError):
        write_vti(tmp_path / "d.vti", {"a": _index_grid(), "b": np.zeros((2, 2, 2))}, {}, SPACING)
    assert list(tmp_path.iterdir()) == []

    # A failed overwrite keeps the old file intact.
    good = tmp_path / "good.vti"
    write_vti(good, {"a": _index_grid()}, {}, SPACING)
    before = good.read_bytes()
    with pytest.raises(TypeError):
        write_vti(good, {"a": np.zeros((NX, NY, NZ), dtype=np.complex128)}, {}, SPACING)
    assert good.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.vti"]


def test_vtk_writer_failure_raises_oserror(small_fs, capfd):
    """A full disk: the VTK writer itself fails half way; its error becomes an OSError that says
    "No space left on device", the old file stays as it was and no temporary file remains."""
    import errno

    folder, readonly = small_fs
    old = folder / "e.vti"
    write_vti(old, {"a": _index_grid()}, {}, SPACING)
    before = old.read_bytes()
    noise = np.random.default_rng(1).random((64, 64, 32)).astype(np.float32)  # 512 KiB, incompressible
    with pytest.raises(OSError, match="No space left on device") as err:
        write_vti(old, {"a": noise}, {}, SPACING)
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(old)
    assert old.read_bytes() == before
    assert sorted(p.name for p in folder.iterdir()) == ["e.vti"]
    # a read-only file system: refused as it is, nothing created
    with pytest.raises(OSError):
        write_vti(readonly / "r.vti", {"a": _index_grid()}, {}, SPACING)
    assert list(readonly.iterdir()) == []
    assert "ERR" not in capfd.readouterr().err


def test_concurrent_writers_never_share_a_file(tmp_path):
    """Writers of one path in several threads: each uses its own temporary file, the survivor
    is one complete file (one writer's data, bit for bit) and nothing temporary remains."""
    import threading

    target = tmp_path / "same.vti"
    grids = [_index_grid() + 1000 * k for k in range(4)]
    errors = []

    def write(k):
        try:
            for _ in range(3):
                write_vti(target, {"a": grids[k]}, {"k": k}, SPACING)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=write, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    arrays, fd = read_vti(target)[:2]
    k = int(fd["k"])
    np.testing.assert_array_equal(arrays["a"], grids[k])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["same.vti"]


def test_read_errors(tmp_path, capfd):
    with pytest.raises(FileNotFoundError):
        read_vti(tmp_path / "nope.vti")

    garbage = tmp_path / "garbage.vti"
    garbage.write_bytes(b"\x00\x01this is not VTK\xff" * 50)
    with pytest.raises(ValueError, match="garbage.vti"):
        read_vti(garbage)

    # A real .vti file cut short: the header parses, the data do not.
    path = tmp_path / "whole.vti"
    write_vti(path, {"a": _index_grid(), "rgba": _rgba()}, {"s": "x"}, SPACING)
    data = path.read_bytes()
    for n, cut in enumerate([len(data) // 3, len(data) - 40]):
        broken = tmp_path / f"cut{n}.vti"
        broken.write_bytes(data[:cut])
        with pytest.raises(ValueError, match=f"cut{n}.vti"):
            read_vti(broken)
    # VTK's complaints end up in the exception, not on stderr.
    assert "ERR" not in capfd.readouterr().err


def test_read_density_array(tmp_path):
    path = tmp_path / "d.vti"
    a = _index_grid()
    write_vti(path, {"density": a, "rgba": _rgba()}, {}, SPACING)
    d = read_density_array(path, "density")
    assert d.dtype == np.float64 and d.shape == (NX, NY, NZ)
    np.testing.assert_array_equal(d, a)

    with pytest.raises(ValueError, match="rho") as info:
        read_density_array(path, "rho")
    assert isinstance(info.value, KeyError) and isinstance(info.value, ArrayNotFoundError)
    assert "density" in str(info.value) and "rgba" in str(info.value)

    with pytest.raises(ValueError, match="components"):
        read_density_array(path, "rgba")
    with pytest.raises(FileNotFoundError):
        read_density_array(tmp_path / "missing.vti", "density")


def test_read_density_array_cell_data(tmp_path):
    """An image whose cells are the voxels: the array has dims - 1 values per axis."""
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData
    from vtkmodules.vtkIOXML import vtkXMLImageDataWriter

    a = _index_grid().astype(np.float64)
    img = vtkImageData()
    img.SetDimensions(NX + 1, NY + 1, NZ + 1)
    arr = numpy_to_vtk(np.ravel(a, order="F"), deep=True)
    arr.SetName("rho")
    img.GetCellData().AddArray(arr)
    path = tmp_path / "cells.vti"
    w = vtkXMLImageDataWriter()
    w.SetInputData(img)
    w.SetFileName(str(path))
    assert w.Write() == 1
    np.testing.assert_array_equal(read_density_array(path, "rho"), a)


# --------------------------------------------------------------------------- rendering


def _blob(color: tuple[float, float, float], n=(24, 20, 16)) -> np.ndarray:
    x, y, z = (np.linspace(-1, 1, k) for k in n)
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    g = np.exp(-(X**2 + Y**2 + Z**2) / 0.2)
    rgba = np.zeros(n + (4,), np.uint8)
    for c in range(3):
        rgba[..., c] = np.round(255 * color[c] * np.sqrt(g)).astype(np.uint8)
    rgba[..., 3] = np.round(255 * g).astype(np.uint8)
    return rgba


def _png_stats(path):
    import matplotlib.image as mpimg

    img = mpimg.imread(str(path))  # float in [0, 1], (h, w, 3 or 4)
    rgb = img[..., :3]
    lit = rgb.max(axis=2) > 0.05  # non-background (background is black)
    return rgb, lit


@pytest.mark.parametrize(
    "color, brighter, dimmer",
    [((0.1, 0.3, 1.0), 2, 0), ((1.0, 0.2, 0.1), 0, 2)],
    ids=["blue", "red"],
)
def test_render_rgba_png_colours(tmp_path, color, brighter, dimmer):
    pytest.importorskip("pyvista")
    from nebula_rt.filters.render import render_rgba_png

    path = tmp_path / "blob.png"
    out = render_rgba_png(path, _blob(color), spacing=(0.1, 0.1, 0.1), window_size=(160, 120))
    assert out == path
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blob.png"]  # no temp file left
    rgb, lit = _png_stats(path)
    assert rgb.shape[:2] == (120, 160)
    assert lit.sum() > 50, "rendered image is blank"
    assert not lit.all(), "no background visible"
    means = rgb[lit].mean(axis=0)
    assert means[brighter] > means[dimmer] + 0.1, means


def test_render_png_from_vti(tmp_path):
    pytest.importorskip("pyvista")
    from nebula_rt.filters.render import render_png_from_vti

    vti = tmp_path / "blob.vti"
    write_vti(vti, {"rgba": _blob((0.1, 1.0, 0.2))}, {}, (0.1, 0.1, 0.1))
    png = render_png_from_vti(vti, tmp_path / "blob.png", window_size=(100, 100))
    rgb, lit = _png_stats(png)
    assert lit.sum() > 50
    means = rgb[lit].mean(axis=0)
    assert means[1] > means[0] and means[1] > means[2]
    with pytest.raises(KeyError, match="nope"):
        render_png_from_vti(vti, tmp_path / "x.png", array_name="nope")


@pytest.mark.parametrize("kind", ["const", "slab", "ramp"])
def test_render_rgba_png_composites_per_voxel(tmp_path, kind):
    """White voxels whose alpha varies along z (constant 20, a 10-layer slab of 30 in an empty
    box, a ramp 0..40), seen straight down -z: the centre pixel is 255 (1 - T) with T the
    transmission of the alpha profile interpolated linearly between the voxel centres,
    exp(integral of ln(1 - alpha/255) dz / h) over the n - 1 intervals (per-voxel compositing,
    the output contract's alpha). Tolerance 4 levels: the renderer samples the profile every
    half voxel (measured within 1.5). The mapper's default transfer-function range (the data's
    alpha range) rendered the slab 26 and the ramp 62."""
    pytest.importorskip("pyvista")
    from nebula_rt.filters.render import render_rgba_png

    n = 32
    alpha = {"const": np.full(n, 20.0), "ramp": np.rint(np.linspace(0, 40, n)),
             "slab": np.where(np.abs(np.arange(n) - n / 2 + 0.5) < 5, 30.0, 0.0)}[kind]
    rgba = np.zeros((n, n, n, 4), np.uint8)  # [x, y, z, channel]
    rgba[..., :3] = 255
    rgba[..., 3] = alpha.astype(np.uint8)[None, None, :]
    path = render_rgba_png(tmp_path / "box.png", rgba, spacing=(1 / n,) * 3, window_size=(120, 120),
                           azimuth=0.0, elevation=0.0)
    import matplotlib.image as mpimg

    centre = 255.0 * mpimg.imread(str(path))[58:62, 58:62, :3].mean()
    z = np.linspace(0.0, n - 1.0, 200 * (n - 1) + 1)
    f = np.log1p(-np.interp(z, np.arange(n), alpha / 255.0))
    expected = 255.0 * (1.0 - np.exp(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(z))))
    assert abs(centre - expected) <= 4.0, (kind, centre, expected)
