"""Proxy ``NebulaLightField`` (Filters > NebulaRT > Nebula Light Field)."""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.bands import PRESETS
from nebula_rt.filters import light_field as _base

from . import _xml

#: default star: centre, luminosity 1, 20 000 K (the bump radius is not used by this filter)
DEFAULT_STAR = (0.5, 0.5, 0.5, 1.0, 20000.0, 0.01)


@smproxy.filter(name="NebulaLightField", label="Nebula Light Field", support_reload=False)
@smhint.xml(_xml.MENU)
@smhint.xml(_xml.LIGHT_FIELD_DISPLAY)
@smproperty.xml(_xml.LIGHT_FIELD_PORTS)
@smproperty.input(name="Input", port_index=0)
@smdomain.datatype(dataTypes=["vtkImageData"], composite_data_supported=False)
@_xml.doc("The vtkImageData holding the dust density (e.g. Nebula Dust Density, or a .vti file).")
@_xml.input_with_array_domain()
class NebulaLightField(_base.NebulaLightField):
    """Traces photon packets from the stars through the input's dust density; adds per band
    ``J_<band>``, ``emissivity_<band>``, ``rel_error_<band>`` and the run's field data."""

    def __init__(self):
        super().__init__()
        self._stars = list(DEFAULT_STAR)

    # -- the repeatable Stars property: RemoveAllStars, then AddStar per star ----------------
    @smproperty.xml(_xml.stars_property(DEFAULT_STAR))
    def AddStar(self, x, y, z, luminosity, temperature, bump_radius):
        self.SetStars(list(self._stars) + [x, y, z, luminosity, temperature, bump_radius])

    def RemoveAllStars(self):
        self.SetStars([])

    # -- the density array ---------------------------------------------------------------------
    @smproperty.xml(_xml.DENSITY_ARRAY)
    def SetInputArrayToProcess(self, *args):
        return super().SetInputArrayToProcess(*args)

    # -- properties (the base class's setters) -------------------------------------------------
    @smproperty.doublevector(name="Albedo", default_values=0.6)
    @smdomain.doublerange(min=0.0, max=1.0)
    @_xml.shown_when("OverrideOptics", 1, mode="enabled_state")
    @_xml.doc("Single-scattering albedo of the dust in every band (with Override Optics).")
    def SetAlbedo(self, v):
        return super().SetAlbedo(v)

    @smproperty.stringvector(name="Backend", default_values="auto", panel_visibility="advanced")
    @_xml.string_list("auto", "opencl", "cuda")
    @_xml.doc("Compute backend: auto (CUDA if usable, else OpenCL), opencl or cuda.")
    def SetBackend(self, name):
        return super().SetBackend(name)

    @smproperty.stringvector(name="BandPreset", label="Band Preset", default_values="thesis-rgb")
    @_xml.string_list(*sorted(PRESETS))
    @_xml.doc("The wavelength bands traced (thesis-rgb: R 677, G 550, B 439 nm with the thesis's "
              "extinction factors 0.748 / 1 / 1.324).")
    def SetBandPreset(self, name):
        return super().SetBandPreset(name)

    @smproperty.intvector(name="BatchSize", label="Batch Size", default_values=0, panel_visibility="advanced")
    @smdomain.intrange(min=0, max=10000000)
    @_xml.doc("Packets per band in one batch, the unit of the Monte Carlo error estimate (0 = automatic: "
              "at least 16 batches). A kernel launch holds one or more batches; progress and cancelling "
              "happen between launches.")
    def SetBatchSize(self, n):
        return super().SetBatchSize(n)

    @smproperty.stringvector(name="Device", default_values="", panel_visibility="advanced")
    @_xml.doc("Compute device: empty = automatic (a GPU if there is one), else a text contained in the "
              "device's name (e.g. NVIDIA, Portable Computing Language).")
    def SetDevice(self, selector):
        # ParaView hands an empty string over as None
        return super().SetDevice(selector or "")

    @smproperty.intvector(name="Estimator", default_values=0)
    @_xml.enumeration("track-length", "collision-filter")
    @_xml.doc("track-length: every packet's path through a voxel scores there (low noise); "
              "collision-filter: the thesis's estimator, collisions spread over Filter Radius.")
    def SetEstimator(self, name):
        return super().SetEstimator(name)

    @smproperty.doublevector(name="FilterRadius", label="Filter Radius", default_values=0.02)
    @smdomain.doublerange(min=0.001, max=0.2)
    @_xml.shown_when("Estimator", 1, mode="enabled_state")
    @_xml.doc("Radius of the collision filter (box units); collision-filter estimator only.")
    def SetFilterRadius(self, r):
        return super().SetFilterRadius(r)

    @smproperty.doublevector(name="G", label="G", default_values=0.6)
    @smdomain.doublerange(min=-1.0, max=1.0)
    @_xml.shown_when("OverrideOptics", 1, mode="enabled_state")
    @_xml.doc("Henyey-Greenstein asymmetry parameter g in every band, in [-1, 1] (with Override Optics).")
    def SetG(self, v):
        return super().SetG(v)

    @smproperty.intvector(name="MaxScatterings", label="Max Scatterings", default_values=1000,
                          panel_visibility="advanced")
    @smdomain.intrange(min=0, max=10000)
    @_xml.doc("A packet is dropped after this many scatterings.")
    def SetMaxScatterings(self, n):
        return super().SetMaxScatterings(n)

    @smproperty.intvector(name="OverrideOptics", label="Override Optics", default_values=1)
    @_xml.boolean()
    @_xml.doc("Use Albedo and G in every band (else the band preset's own values).")
    def SetOverrideOptics(self, flag):
        return super().SetOverrideOptics(flag)

    @smproperty.intvector(name="Quality", default_values=0)
    @_xml.enumeration("custom", "preview", "balanced", "reference")
    @_xml.doc("custom: trace Photons packets (or up to Photons with Target Error); preview / balanced / "
              "reference: trace until the lit region's error is 10 % / 3 % / 1 % (budgets of 10M / 100M / "
              "1000M packets per band).")
    def SetQuality(self, name):
        return super().SetQuality(name)

    @smproperty.doublevector(name="TargetError", label="Target Error", default_values=0.0)
    @smdomain.doublerange(min=0.0, max=0.5)
    @_xml.shown_when("Quality", 0, mode="enabled_state")
    @_xml.doc("0: trace Photons packets. Above 0: trace until the relative error (RMS over the lit "
              "voxels, 1 sigma) is at most this, Photons being the budget.")
    def SetTargetError(self, e):
        return super().SetTargetError(e)

    @smproperty.intvector(name="Photons", default_values=100000)
    @smdomain.intrange(min=1, max=10000000)
    @_xml.doc("Photon packets per band. Noise falls as 1/sqrt(Photons); the thesis used 2.1 million.")
    def SetPhotons(self, n):
        return super().SetPhotons(n)

    @smproperty.intvector(name="Seed", default_values=1, panel_visibility="advanced")
    @smdomain.intrange(min=0, max=2147483647)
    @_xml.doc("Random seed: the same seed, scene and device give the same result.")
    def SetSeed(self, s):
        return super().SetSeed(s)

    @smproperty.doublevector(name="Tau", default_values=128.0)
    @smdomain.doublerange(min=0.0, max=256.0)
    @_xml.doc("Optical depth across one box edge at density 1 in the reference band (thesis: 128, "
              "i.e. extinction = density per voxel of a 128^3 grid).")
    def SetTau(self, v):
        return super().SetTau(v)

    @smproperty.xml(_xml.property_groups(
        ("Dust", ["DensityArray", "Tau"]),
        ("Stars", ["Stars"]),
        ("Dust optics", ["BandPreset", "OverrideOptics", "Albedo", "G"]),
        ("Photon transport", ["Quality", "TargetError", "Photons", "Estimator", "FilterRadius", "MaxScatterings", "Seed"]),
        ("Compute device", ["Backend", "Device", "BatchSize"]),
    ))
    def zz_property_groups(self):
        """Carries the PropertyGroups (its name sorts last)."""
