"""The dust density on the grid: generated on the device (the models are kernels in
``kernels/density.cl``: turbulence, uniform, each star's bump) or read from a file
(:mod:`~nebula_rt.density.generate`); the voxel averages of a field given on boxes, an
adaptive grid's leaves (:mod:`~nebula_rt.density.resample`)."""

from .generate import check_density_file, file_digest, generate_density, load_density_file
from .resample import box_averages

__all__ = ["box_averages", "check_density_file", "file_digest", "generate_density", "load_density_file"]
