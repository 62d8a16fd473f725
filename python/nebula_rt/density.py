"""Dust density stage: turbulence, uniform or user-supplied density on the voxel grid.

All models share one formula (thesis Eq. 3.2 and 3.3, generalised):

    rho = max(floor, base + sum over stars of the voxel-averaged cubic bump)

with base = scale * max(0, turbulence(v + offset)) ("turbulence"), a constant ("uniform"),
or the array read from ``dust.file`` ("file"). The generated models run on the compute
device; ``nebula_rt.reference_density`` is an independent NumPy implementation used as the
test oracle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .backends import Backend
from .backends.base import MODEL_TURBULENCE, MODEL_UNIFORM
from .errors import SceneError

#: Midpoint samples per axis used to average a star's bump over a voxel.
BUMP_SUBSAMPLES = 8


def _stars_array(stars) -> np.ndarray:
    return np.array([[*s.position, s.bump_radius] for s in stars], dtype=np.float32).reshape(-1, 4)


def load_density_file(path: Path, array: str, shape: tuple[int, int, int]) -> np.ndarray:
    """Read a density array from ``.npy`` (x, y, z order) or ``.vti`` and check it.

    Raises
    ------
    SceneError
        ``dust.file`` unreadable, of another shape than ``grid.shape``, or holding negative,
        NaN or infinite values.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError("dust.file", str(path), "must name an existing .npy or .vti file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            data = np.load(path, allow_pickle=False)
        elif suffix == ".vti":
            from .io_vti import read_density_array

            data = read_density_array(path, array)
        else:
            raise SceneError("dust.file", str(path), "must be a .npy or .vti file")
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
    return data


def generate_density(scene, backend: Backend) -> np.ndarray:
    """Density of ``scene`` on its grid, float32 (nx, ny, nz) (index [i, j, k] = x, y, z)."""
    from .resources import check_density

    dust = scene.dust
    shape = tuple(scene.grid.shape)
    check_density(shape, backend)
    stars = _stars_array(scene.stars)
    if dust.model == "turbulence":
        return backend.generate_density(
            shape, MODEL_TURBULENCE, dust.offset, dust.scale, 0.0, dust.floor, stars, BUMP_SUBSAMPLES
        )
    if dust.model == "uniform":
        return backend.generate_density(
            shape, MODEL_UNIFORM, (0.0, 0.0, 0.0), 0.0, dust.density, dust.floor, stars, BUMP_SUBSAMPLES
        )
    if dust.model == "file":
        data = load_density_file(scene.dust_file_path(), dust.array, shape)
        if np.any(stars[:, 3] > 0):
            data = data + backend.generate_density(
                shape, MODEL_UNIFORM, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0, stars, BUMP_SUBSAMPLES
            )
        return np.maximum(data, dust.floor).astype(np.float32)
    raise SceneError("dust.model", dust.model, "one of: 'turbulence', 'uniform', 'file'")
