"""VTK algorithms of NebulaRT (``nebula_rt.filters``): usable from plain VTK, pyvista and,
through the thin wrappers of ``plugin/``, ParaView.

- :class:`NebulaDustDensity`  source  -> vtkImageData with ``density``
- :class:`NebulaLightField`   filter  vtkImageData (a density array) -> the light field
- :class:`NebulaColour`       filter  light field -> ``rgba`` (+ ``rgb_linear``), no re-trace
- :class:`NebulaSkyImage`     filter  light field -> 2D image of what a telescope sees

Each is a ``VTKPythonAlgorithmBase``: setters only store the value and call ``Modified()``;
validation happens in ``RequestData`` with the library's errors (an invalid value produces an
empty output, a VTK error message naming the parameter, and ``last_error``); progress is
reported per kernel launch through ``UpdateProgress``/``SetProgressText`` and ``CheckAbort`` cancels
between batches. VTK's pipeline re-executes only the algorithms whose inputs or properties
changed; ``execution_count`` counts real executions.
"""

from .colour import NebulaColour
from .dust_density import NebulaDustDensity
from .light_field import NebulaLightField
from .sky_image import NebulaSkyImage

__all__ = ["NebulaColour", "NebulaDustDensity", "NebulaLightField", "NebulaSkyImage"]
