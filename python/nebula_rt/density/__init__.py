"""The dust density on the grid: generated on the device (the models are kernels in
``kernels/density.cl``: turbulence, uniform, each star's bump) or read from a file
(:mod:`~nebula_rt.density.generate`); the voxel averages of a field given on boxes, an
adaptive grid's leaves (:mod:`~nebula_rt.density.resample`); an adaptive density as a forest of
octrees in flat arrays (:mod:`~nebula_rt.density.octree`; docs/adaptive_grids.md), particle
snapshots deposited on one (:mod:`~nebula_rt.density.particles`), the procedural density refined
on one (:mod:`~nebula_rt.density.procedural_tree`), and the stars' bumps over leaves
(:mod:`~nebula_rt.density.bumps`)."""

from .generate import (check_density_file, file_digest, generate_density, is_adaptive_file, load_density_file,
                       load_tree, scene_density, traced_on_tree)
from .procedural_tree import procedural_tree
from .octree import Octree, coarsen, from_boxes
from .resample import box_averages

__all__ = ["Octree", "box_averages", "check_density_file", "coarsen", "file_digest", "from_boxes", "generate_density",
           "is_adaptive_file", "load_density_file", "load_tree", "procedural_tree", "scene_density", "traced_on_tree"]
