"""Proxy ``NebulaDustDensity`` (Sources > NebulaRT > Nebula Dust Density)."""

from paraview.util.vtkAlgorithm import smdomain, smhint, smproperty, smproxy

from nebula_rt.filters import dust_density as _base

from . import _xml

#: default star: centre, luminosity 1, 20 000 K, bump radius 0.01 (the thesis's default nebula)
DEFAULT_STAR = (0.5, 0.5, 0.5, 1.0, 20000.0, 0.01)


@smproxy.source(name="NebulaDustDensity", label="Nebula Dust Density", support_reload=False)
@smhint.xml(_xml.MENU)
@smhint.xml(_xml.VOLUME)
class NebulaDustDensity(_base.NebulaDustDensity):
    """Dust density on an nx x ny x nz grid spanning the box [0, 1]^3 (thesis Eq. 3.2/3.3):
    point array ``density`` on the voxel centres."""

    def __init__(self):
        super().__init__()
        self._stars = list(DEFAULT_STAR)

    # -- the repeatable Stars property: RemoveAllStars, then AddStar per star ----------------
    @smproperty.xml(_xml.stars_property(DEFAULT_STAR))
    def AddStar(self, x, y, z, luminosity, temperature, bump_radius):
        self.SetStars(list(self._stars) + [x, y, z, luminosity, temperature, bump_radius])

    def RemoveAllStars(self):
        self.SetStars([])

    # -- properties (the base class's setters) -------------------------------------------------
    @smproperty.stringvector(name="Backend", default_values="auto", panel_visibility="advanced")
    @_xml.string_list("auto", "opencl", "cuda")
    @_xml.doc("Compute backend for the density kernel: auto (CUDA if usable, else OpenCL), opencl or cuda.")
    def SetBackend(self, name):
        return super().SetBackend(name)

    @smproperty.stringvector(name="Device", default_values="", panel_visibility="advanced")
    @_xml.doc("Compute device: empty = automatic (a GPU if there is one), else a text contained in the "
              "device's name (e.g. NVIDIA, Portable Computing Language).")
    def SetDevice(self, selector):
        # ParaView hands an empty string over as None
        return super().SetDevice(selector or "")

    @smproperty.doublevector(name="Floor", default_values=1e-4, panel_visibility="advanced")
    @smdomain.doublerange(min=0.0, max=0.01)
    @_xml.doc("Minimum density everywhere (keeps the medium from being empty).")
    def SetFloor(self, v):
        return super().SetFloor(v)

    @smproperty.intvector(name="GridShape", label="Grid Shape", default_values=[64, 64, 64])
    @smdomain.intrange(min=2, max=512)
    @_xml.doc("Voxels along x, y, z. The grid spans the box [0, 1]^3: spacing 1/n. Memory and trace "
              "time grow with the number of voxels (the thesis used 128^3).")
    def SetGridShape(self, nx, ny, nz):
        return super().SetGridShape(nx, ny, nz)

    @smproperty.intvector(name="Model", default_values=0)
    @_xml.enumeration("turbulence", "uniform")
    @_xml.doc("turbulence: smooth noise (thesis Eq. 3.2); uniform: constant density. Both plus each "
              "star's dust bump and the floor.")
    def SetModel(self, model):
        return super().SetModel(model)

    @smproperty.doublevector(name="Offset", default_values=[0.5, 0.5, 0.5])
    @_xml.shown_when("Model", 0)
    @_xml.doc("Noise-space offset of the turbulence (box units): a different offset gives a different nebula.")
    def SetOffset(self, x, y, z):
        return super().SetOffset(x, y, z)

    @smproperty.doublevector(name="Scale", default_values=0.15)
    @smdomain.doublerange(min=0.0, max=1.0)
    @_xml.shown_when("Model", 0)
    @_xml.doc("Amplitude of the turbulence (thesis: 0.15).")
    def SetScale(self, v):
        return super().SetScale(v)

    @smproperty.doublevector(name="UniformDensity", label="Uniform Density", default_values=1.0)
    @smdomain.doublerange(min=0.0, max=1.0)
    @_xml.shown_when("Model", 1)
    @_xml.doc("Density of the uniform model (the light field's Tau is the optical depth across the "
              "box at density 1).")
    def SetUniformDensity(self, v):
        return super().SetUniformDensity(v)

    @smproperty.xml(_xml.property_groups(
        ("Dust", ["GridShape", "Model", "Scale", "Offset", "UniformDensity", "Floor"]),
        ("Stars", ["Stars"]),
        ("Compute device", ["Backend", "Device"]),
    ))
    def zz_property_groups(self):
        """Carries the PropertyGroups (its name sorts last)."""
