"""Reader ``NebulaFitResultReader`` (File > Open, "NebulaRT fit result (*.json)").

Opens what ``nebula-rt fit ... --json FILE`` writes: output port "Parameters" (the best-fit
values with their 1-sigma errors and bounds, chi^2 in the field data) and port "Comparison"
(the best fit against every observed table, for a spreadsheet or a line chart of ``data`` and
``model`` over ``x``); see :mod:`nebula_rt.filters.fit_result`. In pvpython:
``OpenDataFile("fit.json")`` or ``NebulaFitResultReader(FileName="fit.json")``.
"""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import fit_result as _base

from . import _xml

PORTS = '<OutputPort name="Parameters" index="0" /><OutputPort name="Comparison" index="1" />'


@smproxy.reader(name="NebulaFitResultReader", label="Nebula Fit Result Reader", extensions="json",
                file_description="NebulaRT fit result", support_reload=False)
@_xml.proxy_doc(_base.NebulaFitResultReader)
@smproperty.xml(PORTS)
class NebulaFitResultReader(_base.NebulaFitResultReader):
    """The parameters and the best fit against the tables of a ``nebula-rt fit --json`` file."""

    @smproperty.stringvector(name="FileName", panel_visibility="never")
    @smdomain.filelist()
    @smhint.filechooser(extensions="json", file_description="NebulaRT fit result")
    def SetFileName(self, name):
        return super().SetFileName(name)
