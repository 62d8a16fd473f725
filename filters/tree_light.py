"""The light per leaf of a run on an adaptive density, written as a vtkHyperTreeGrid
(``nebula-rt render --tree``). Apart from :mod:`nebula_rt.filters.adaptive`, which the density
stage reads adaptive files with: this module names the output contract (the pipeline), which
the density stage sits below."""

from __future__ import annotations

import numpy as np

from nebula_rt.density.octree import Octree
from nebula_rt.pipeline import output_contract as contract

from .adaptive import octree_to_htg

__all__ = ["tree_light_htg", "write_tree_light"]


def write_tree_light(path, tree: Octree, light) -> None:
    """Write the light per leaf of a run on ``tree`` (:func:`tree_light_htg`, over the unit
    box) to ``path`` (.htg)."""
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridWriter

    writer = vtkXMLHyperTreeGridWriter()
    writer.SetInputData(tree_light_htg(tree, light))
    writer.SetFileName(str(path))
    if writer.Write() != 1:
        raise OSError(f"VTK's vtkXMLHyperTreeGridWriter could not write {path}")


def tree_light_htg(tree: Octree, light, bounds=(0.0, 1.0, 0.0, 1.0, 0.0, 1.0)):
    """The light per leaf of a run on ``tree`` (``light``: its
    :class:`~nebula_rt.pipeline.stages.LightField`, whose transport holds J and the relative
    error per leaf) as cell data of a vtkHyperTreeGrid over ``bounds``: per band ``J_<band>``,
    ``rel_error_<band>`` and ``emissivity_<band>`` (alb x sigma x rho x J, formed per leaf), and
    ``density``; a refined cell holds its children's mean (:func:`octree_to_htg`). The names are
    the output contract's."""
    res = light.transport
    rho = np.asarray(tree.density, np.float64)
    arrays = {contract.DENSITY.name(): tree.density}
    for b, band in enumerate(light.bands):
        sigma = light.scene.dust.tau * band.extinction
        arrays[contract.J.name(band.name)] = res.J[b].astype(np.float32)
        arrays[contract.REL_ERROR.name(band.name)] = res.rel_error[b].astype(np.float32)
        arrays[contract.EMISSIVITY.name(band.name)] = (band.albedo * sigma * rho * res.J[b]).astype(np.float32)
    return octree_to_htg(tree, arrays, bounds)
