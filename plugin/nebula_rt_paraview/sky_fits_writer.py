"""Writer ``NebulaSkyFitsWriter`` (File > Save Data, "NebulaRT calibrated sky image (*.fits)").

Writes the output of Nebula Sky Image with Units "MJy/sr" as FITS: one image HDU per band
(``SB_<band>``, MJy/sr) and per passband (``MAG_BESSELL_B`` ... ``MAG_SDSS_I``, AB
mag/arcsec^2), each with the celestial WCS (:func:`nebula_rt.filters.sky_image.write_fits`).
In pvpython: ``SaveData("sky.fits", proxy=sky)``.
"""

from paraview.util.vtkAlgorithm import smdomain, smproperty, smproxy

from nebula_rt.filters import sky_image as _base


@smproxy.writer(extensions="fits", file_description="NebulaRT calibrated sky image", support_reload=False)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
class NebulaSkyFitsWriter(_base.NebulaSkyFitsWriter):
    """A calibrated sky image (Nebula Sky Image, Units MJy/sr) as FITS with a celestial WCS."""

    @smproperty.stringvector(name="FileName", panel_visibility="never")
    @smdomain.filelist()
    def SetFileName(self, name):
        return super().SetFileName(name)
