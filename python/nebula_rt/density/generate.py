"""Dust density stage: turbulence, uniform or user-supplied density on the voxel grid.

All models share one formula (thesis Eq. 3.2 and 3.3, generalised):

    rho = max(floor, base + sum over stars of the voxel-averaged cubic bump)

with base = scale * max(0, turbulence(v + offset)) ("turbulence"), a constant ("uniform"),
or the array read from ``dust.file`` ("file"). The generated models run on the compute
device; an independent NumPy implementation, ``tests/oracles/reference_density.py``, is the
test oracle.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import math

import numpy as np

from .. import limits
from ..backends import Backend
from ..backends.base import MODEL_TURBULENCE, MODEL_UNIFORM
from ..errors import SceneError
from ..input_files import check_input_file, open_input
from .bumps import BUMP_SUBSAMPLES, leaf_bumps, stars_array as _stars_array
from .procedural_tree import procedural_tree

def file_digest(path: Path) -> str:
    """SHA-256 (hex) of a file's bytes: identifies a density file by its content (a file
    rewritten with its modification time kept is still recognised as changed).

    Raises
    ------
    SceneError
        ``dust.file`` is not an existing, readable regular file (a FIFO or a device would
        never end the hash: :mod:`nebula_rt.input_files`).
    """
    h = hashlib.sha256()
    with open_input("dust.file", path, DENSITY_FILE) as fh:
        for chunk in iter(lambda: fh.read(1 << 22), b""):
            h.update(chunk)
    return h.hexdigest()


#: what ``dust.file`` must be, for the refusals
DENSITY_FILE = "an existing .npy, .vti, .htg, .vthb or .vtp file"

#: adaptive densities (VTK's XML hyper tree grid and overlapping AMR files, and SPH particle
#: snapshots as XML poly data), made into an :class:`~nebula_rt.density.octree.Octree`
#: (nebula_rt.filters.adaptive reads them)
ADAPTIVE_SUFFIXES = (".htg", ".vthb", ".vtkhdf", ".hdf", ".vtp")


def is_adaptive_file(path) -> bool:
    """Whether a ``dust.file`` holds an adaptive density (by its suffix)."""
    return Path(path).suffix.lower() in ADAPTIVE_SUFFIXES


def _npy_header_shape(fh, path: Path, shape: tuple[int, int, int]) -> np.dtype:
    """Check a ``.npy`` header before its data is read: the array it claims must have the
    grid's shape (a crafted header claiming 2^40 values is refused without allocating).
    Returns the header's dtype, ``fh`` at the first byte of the data."""
    try:
        version = np.lib.format.read_magic(fh)
        read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        claimed, _fortran, dtype = read(fh)
    except Exception as exc:  # not a .npy header: numpy's words say why
        raise SceneError("dust.file", str(path), f"could not be read as density data ({exc})") from None
    if tuple(claimed) != tuple(shape):
        raise SceneError("dust.file", str(path),
                         f"array shape {tuple(claimed)} must equal grid.shape {tuple(shape)}")
    if dtype.kind not in "fiu":
        raise SceneError("dust.file", str(path), f"must hold a numeric array (found dtype {dtype})")
    return dtype


#: Bytes a ``.vti`` may spend on a value of one of its arrays at most (a float64 as ASCII text
#: with its separator takes at most 25; binary, base64 or compressed take less), on the XML
#: around the arrays, and the components an array may have (a 3 x 3 tensor): a density file
#: larger than its header's arrays can take up is refused before it is hashed or read.
VTI_BYTES_PER_VALUE = 32
VTI_XML_BYTES = 1 << 20
VTI_MAX_COMPONENTS = 9


def check_density_file(path: Path, array: str, shape: tuple[int, int, int]) -> None:
    """What can be told of ``dust.file`` before its data is read, in milliseconds: a regular,
    readable file; a ``.npy`` whose header declares the grid's shape, a numeric type and
    exactly the bytes the file holds; a ``.vti`` whose header declares ``array`` on the grid's
    shape, and no more bytes than its arrays can take up (:data:`VTI_BYTES_PER_VALUE`).

    The command line's start-up checks a scene's density file here, before the device is
    opened and before the file is hashed (:func:`file_digest` reads all of it: a 100 GB file
    behind a valid header took minutes), as :meth:`nebula_rt.pipeline.stages.Pipeline.run` does.

    Raises
    ------
    SceneError
        Naming ``dust.file``, the path and why.
    """
    path = Path(path)
    st = check_input_file("dust.file", path, DENSITY_FILE)
    suffix = path.suffix.lower()
    if suffix == ".npy":
        with open_input("dust.file", path, DENSITY_FILE) as fh:
            dtype = _npy_header_shape(fh, path, shape)
            declared = fh.tell() + math.prod(shape) * dtype.itemsize
        if st.st_size != declared:
            raise SceneError("dust.file", str(path), f"holds {st.st_size} bytes, its .npy header declares {declared} "
                                                     f"(a {dtype} array of shape {tuple(shape)}): a truncated or "
                                                     "damaged file")
    elif suffix == ".vti":
        try:
            from ..filters.density_file import declared_density
        except ImportError as exc:
            raise SceneError("dust.file", str(path), f"a .vti density needs {(exc.name or 'vtk').split('.')[0]}: "
                                                     "pip install 'nebula-rt[io]', or give a .npy file") from None
        try:
            points, arrays = declared_density(path, array, expected_shape=shape)
        except SceneError:
            raise
        except Exception as exc:  # unreadable header: say which file and why
            raise SceneError("dust.file", str(path), f"could not be read as density data ({exc})") from None
        most = VTI_XML_BYTES + arrays * VTI_MAX_COMPONENTS * VTI_BYTES_PER_VALUE * math.prod(points)
        if st.st_size > most:
            raise SceneError("dust.file", str(path), f"{st.st_size} bytes, more than the {most} its header's {arrays} "
                                                     f"array(s) of {math.prod(points)} points can take up: a damaged "
                                                     "file")
    elif suffix not in ADAPTIVE_SUFFIXES:  # (an adaptive file is checked as it is read: load_tree)
        raise SceneError("dust.file", str(path), "must be a .npy, .vti, .htg, .vthb, .vtkhdf, .hdf or .vtp file")


def load_density_file(path: Path, array: str, shape: tuple[int, int, int]) -> np.ndarray:
    """Read a density array from ``.npy`` (x, y, z order) or ``.vti`` and check it.

    Raises
    ------
    SceneError
        ``dust.file`` unreadable, of another shape than ``grid.shape``, or holding negative,
        NaN or infinite values, or values float32 cannot hold (above 3.4e38, or non-zero below
        1.2e-38: the transport's density is float32).
    """
    path = Path(path)
    check_input_file("dust.file", path, DENSITY_FILE)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            with open_input("dust.file", path, DENSITY_FILE) as fh:
                _npy_header_shape(fh, path, shape)
                fh.seek(0)
                data = np.load(fh, allow_pickle=False)
        elif suffix == ".vti":
            try:  # the VTK layer: VTK's own reader (the io extra, or ParaView's VTK; no pyvista needed)
                from ..filters.density_file import read_density_array
            except ImportError as exc:
                raise SceneError("dust.file", str(path), f"a .vti density needs {(exc.name or 'vtk').split('.')[0]}: "
                                                         "pip install 'nebula-rt[io]', or give a .npy file") from None
            data = read_density_array(path, array, expected_shape=shape)
        else:
            raise SceneError("dust.file", str(path), "must be a .npy or .vti file (an adaptive .htg or "
                                                     ".vthb density is read by load_tree)")
    except SceneError:
        raise
    except Exception as exc:  # unreadable file: say which and why
        raise SceneError("dust.file", str(path), f"could not be read as density data ({exc})") from exc
    data = np.asarray(data)
    if data.dtype.kind not in "fiu":
        raise SceneError("dust.file", str(path), f"must hold a numeric array (found dtype {data.dtype})")
    if tuple(data.shape) != tuple(shape):
        raise SceneError(
            "dust.file", str(path), f"array shape {tuple(data.shape)} must equal grid.shape {tuple(shape)}"
        )
    data = data.astype(np.float64)
    if not np.all(np.isfinite(data)):
        raise SceneError("dust.file", str(path), "density must be finite (found NaN or infinity)")
    if np.any(data < 0):
        raise SceneError("dust.file", str(path), f"density must be >= 0 (minimum found {data.min()!r})")
    limits.check_float32_array("dust.file", str(path), data, "density values")
    return data


#: Largest value of the turbulence sum: sum over the octaves of max|noise| / f, |noise| <= 1,
#: f = 2^e for e in {0.05, 2, 4, 6, 12, 8, 0} (kernels/nebula_common.h).
TURBULENCE_MAX = sum(2.0 ** -e for e in (0.05, 2, 4, 6, 12, 8, 0))


def _check_generated(scene, rho: np.ndarray, backend: Backend) -> np.ndarray:
    """The device density must be finite: scale x turbulence (or density) plus the stars' bumps
    may pass float32's range although each parameter is within it."""
    extremes = backend.density_extremes(rho)
    if extremes is None:  # on the host: two reductions, no temporaries (NaN propagates through max)
        extremes = (float(rho.min()), float(rho.max())) if rho.size else (0.0, 0.0)
    finite = math.isfinite(extremes[0]) and math.isfinite(extremes[1])
    if finite:
        return rho
    dust = scene.dust
    n = len(scene.stars)
    if dust.model == "turbulence":
        raise SceneError("dust.scale", dust.scale, f"scale x turbulence (up to {TURBULENCE_MAX:.4f}) plus the "
                                                   f"stars' bumps overflows float32: allowed scale <= "
                                                   f"{limits.fmt((limits.FLOAT32_MAX - n) / TURBULENCE_MAX)}")
    raise SceneError("dust.density", dust.density, f"density plus the stars' bumps (up to {n}) overflows float32: "
                                                   f"allowed density <= {limits.fmt(limits.FLOAT32_MAX - n)}")


def load_tree(scene):
    """The adaptive density of ``scene``: an :class:`~nebula_rt.density.octree.Octree` over the
    unit box, the stars' bumps added and each leaf at least ``dust.floor``. ``dust.file`` a
    ``.htg`` or ``.vthb`` (its cell array ``dust.array``), or a ``.vtp`` particle snapshot
    (:func:`particle_tree`).

    Raises
    ------
    SceneError
        ``dust.file`` unreadable, not a hyper tree grid or AMR hierarchy an octree can hold
        (nebula_rt.filters.adaptive says why), or with values float32 cannot hold.
    """
    from .octree import Octree

    path = Path(scene.dust_file_path())
    check_input_file("dust.file", path, DENSITY_FILE)
    if scene.dust.octree and path.suffix.lower() != ".vtp":
        raise SceneError("dust.octree", True, f"refines the procedural models and particle snapshots (.vtp); "
                                              f"{path.name} is a tree already, refined as it was written")
    try:  # the VTK layer: VTK's own XML readers (the io extra, or ParaView's VTK)
        from ..filters.adaptive import read_adaptive_density, read_particles
    except ImportError as exc:
        raise SceneError("dust.file", str(path), f"an adaptive density needs {(exc.name or 'vtk').split('.')[0]}: "
                                                 "pip install 'nebula-rt[io]'") from None
    try:
        if path.suffix.lower() == ".vtp":
            tree = particle_tree(scene, *read_particles(path, scene.dust.particle_mass, scene.dust.particle_smoothing))
        else:
            tree = read_adaptive_density(path, scene.dust.array)
    except ValueError as exc:
        raise SceneError("dust.file", str(path), f"could not be read as an adaptive density: {exc}") from None
    lo, hi, _ = tree.leaves()
    rho = np.asarray(tree.density, np.float64) + leaf_bumps(lo, hi, _stars_array(scene.stars))
    rho = np.maximum(rho, scene.dust.floor)
    if not rho.max(initial=0.0) <= limits.FLOAT32_MAX:
        raise SceneError("dust.file", str(path), f"density values must stay within float32 (at most "
                                                 f"{limits.fmt(limits.FLOAT32_MAX)}; found {limits.fmt(float(rho.max()))})")
    return Octree(tree.roots, tree.child, rho.astype(np.float32))


def particle_tree(scene, positions, masses, smoothing):
    """The octree of a particle snapshot (:mod:`nebula_rt.density.particles`): positions and
    smoothing lengths (the snapshot's coordinates, grid.unit) into box units by the box of edge
    ``grid.length`` from ``dust.particle_origin``; cells split while they hold more than
    ``dust.leaf_particles`` particles (and, with ``dust.octree``, while their optical depth
    across it exceeds ``dust.cell_tau``), down to ``dust.tree_depth`` levels; each leaf's density
    its deposited mass over its volume (box units). ValueError names a particle outside the
    box, or a non-finite or negative value."""
    from .particles import particles_on_tree
    from ..scene.units import length_metres

    grid, dust = scene.grid, scene.dust
    edge = length_metres(grid.length, grid.unit) / length_metres(1.0, grid.unit)  # in grid.unit
    p = (np.asarray(positions, np.float64) - np.asarray(dust.particle_origin, np.float64)[None, :]) / edge
    h = np.asarray(smoothing, np.float64) / edge
    outside = np.flatnonzero(~np.all((p >= 0.0) & (p <= 1.0), axis=1))
    if outside.size:
        i = outside[0]
        raise ValueError(f"particle {i} at {np.asarray(positions)[i].tolist()} ({grid.unit}) lies outside the box "
                         f"of edge {edge:g} {grid.unit} from dust.particle_origin {list(dust.particle_origin)} "
                         f"({outside.size} of {len(p)} particles do)")
    if dust.octree:  # also split by the particles' optical depth per cell (dust.cell_tau)
        from ..optics.bands import reference_band_index

        bands = scene.bands.resolve()
        sigma = float(dust.tau) * float(bands[reference_band_index(bands)].extinction)
        return particles_on_tree(p, masses, h, dust.leaf_particles, dust.tree_depth, sigma, dust.cell_tau)
    return particles_on_tree(p, masses, h, dust.leaf_particles, dust.tree_depth)


def traced_on_tree(scene) -> bool:
    """Whether ``scene``'s density is an octree: an adaptive ``dust.file`` or ``dust.octree``."""
    if scene.dust.model == "file":
        return is_adaptive_file(scene.dust_file_path())
    return bool(scene.dust.octree)


def scene_density(scene, backend: Backend):
    """The density a scene is traced through: an :class:`~nebula_rt.density.octree.Octree`
    for an adaptive ``dust.file`` (:func:`load_tree`) or with ``dust.octree``
    (:func:`~nebula_rt.density.procedural_tree.procedural_tree`), else the grid of
    :func:`generate_density`."""
    if scene.dust.model == "file" and is_adaptive_file(scene.dust_file_path()):
        return load_tree(scene)
    if scene.dust.octree:
        return procedural_tree(scene, backend)
    return generate_density(scene, backend)


def generate_density(scene, backend: Backend) -> np.ndarray:
    """Density of ``scene`` on its grid, float32 (nx, ny, nz) (index [i, j, k] = x, y, z).

    An adaptive ``dust.file`` or ``dust.octree`` is refused here: everything that traces takes
    the tree from :func:`scene_density`; the Dust Density source, which shows the grid, only a
    uniform one."""
    dust = scene.dust
    shape = tuple(scene.grid.shape)
    stars = _stars_array(scene.stars)
    if dust.model == "file" and is_adaptive_file(scene.dust_file_path()):
        raise SceneError("dust.file", str(scene.dust_file_path()),
                         "an adaptive density (.htg, .vthb, .vtp) is an octree, traced leaf by leaf "
                         "(scene_density); the Dust Density source makes a uniform grid (.npy or .vti) only: "
                         "open the file with ParaView's reader instead")
    if dust.octree:
        raise SceneError("dust.octree", True,
                         "an octree density is traced leaf by leaf (scene_density); the Dust Density source "
                         "makes a uniform grid only (dust.octree = false)")
    if dust.model == "file":
        data = load_density_file(scene.dust_file_path(), dust.array, shape)
        if np.any(stars[:, 3] > 0):
            backend.check_grid_fits(shape)
            data = data + backend.generate_density(
                shape, MODEL_UNIFORM, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0, stars, BUMP_SUBSAMPLES
            )
        data = np.maximum(data, dust.floor)
        if not data.max() <= limits.FLOAT32_MAX:
            raise SceneError("dust.file", str(scene.dust_file_path()),
                             f"density values plus the stars' bumps must stay within float32 (at most "
                             f"{limits.fmt(limits.FLOAT32_MAX)}; found {limits.fmt(float(data.max()))})")
        return data.astype(np.float32)
    backend.check_grid_fits(shape)
    if dust.model == "turbulence":
        return _check_generated(scene, backend.generate_density(
            shape, MODEL_TURBULENCE, dust.offset, dust.scale, 0.0, dust.floor, stars, BUMP_SUBSAMPLES
        ), backend)
    if dust.model == "uniform":
        return _check_generated(scene, backend.generate_density(
            shape, MODEL_UNIFORM, (0.0, 0.0, 0.0), 0.0, dust.density, dust.floor, stars, BUMP_SUBSAMPLES
        ), backend)
    raise SceneError("dust.model", dust.model, "one of: 'turbulence', 'uniform', 'file'")
