"""VTK algorithms of NebulaRT (``nebula_rt.filters``): usable from plain VTK, pyvista and,
through the thin wrappers of ``plugin/``, ParaView.

- :class:`NebulaDustDensity`  source  -> vtkImageData with ``density``
- :class:`NebulaLightField`   filter  vtkImageData (a density array) -> the light field
- :class:`NebulaColour`       filter  light field -> ``rgba`` (+ ``rgb_linear``), no re-trace
- :class:`NebulaSkyImage`     filter  light field -> 2D image of what a telescope sees
  (with Units "MJy/sr" also calibrated: surface brightness, magnitudes, a celestial WCS)
- :class:`NebulaPolarizationVectors` filter  polarized sky image -> points with polarization vectors
  (to glyph: the pattern about the star)
- :class:`NebulaSkyFitsWriter` writer  calibrated sky image -> FITS
- :class:`NebulaFitResultReader` reader  `nebula-rt fit --json` -> parameters and comparison tables

Each is a ``VTKPythonAlgorithmBase``: setters only store the value and call ``Modified()``;
validation happens in ``RequestData`` with the library's errors (an invalid value produces an
empty output, a VTK error message naming the parameter, and ``last_error``); progress is
reported per kernel launch through ``UpdateProgress``/``SetProgressText`` and ``CheckAbort`` cancels
between batches. VTK's pipeline re-executes only the algorithms whose inputs or properties
changed; ``execution_count`` counts real executions.

The rest of NebulaRT's VTK layer (the library, ``nebula_rt``, imports no VTK) lives here too:

- :mod:`nebula_rt.filters.image_data`  NumPy grids and field data in a vtkImageData
- :mod:`nebula_rt.filters.vti`         reading and writing ``.vti`` files (the ``io`` extra)
- :mod:`nebula_rt.filters.render`      off-screen PNG volume rendering with pyvista (``io``)
- :mod:`nebula_rt.filters.controller`  the communicator of ParaView's parallel engine
- :mod:`nebula_rt.filters.adaptive`    hyper tree grids to and from the library's octrees

The names and types of the outputs' arrays and field data are declared in
:mod:`nebula_rt.pipeline.output_contract`.
"""

from .colour import NebulaColour
from .dust_density import NebulaDustDensity
from .fit_result import NebulaFitResultReader
from .light_field import NebulaLightField
from .polarization_vectors import NebulaPolarizationVectors
from .sky_image import NebulaSkyFitsWriter, NebulaSkyImage

__all__ = ["NebulaColour", "NebulaDustDensity", "NebulaFitResultReader", "NebulaLightField",
           "NebulaPolarizationVectors", "NebulaSkyFitsWriter", "NebulaSkyImage"]
