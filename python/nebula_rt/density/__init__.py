"""The dust density on the grid: generated on the device (the models are kernels in
``kernels/density.cl``: turbulence, uniform, each star's bump) or read from a file
(:mod:`~nebula_rt.density.generate`)."""

from .generate import check_density_file, file_digest, generate_density, load_density_file

__all__ = ["check_density_file", "file_digest", "generate_density", "load_density_file"]
