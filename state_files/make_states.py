"""Regenerate the ParaView state files of the thesis's result figures (run with pvpython).

    source scripts/pv-env.sh
    pvpython state_files/make_states.py                      # writes state_files/*.pvsm
    pvpython state_files/make_states.py --grid 128 --photons 2100000 --out /tmp/big
    pvpython state_files/make_states.py --screenshots docs/images   # + paraview-fig4_*.png

States (each: one Nebula Dust Density feeding four Nebula Light Field -> Nebula Colour
branches, albedo 0.2 / 0.4 / 0.6 / 0.8, shown side by side as rgba volumes with their stars,
one shared fixed exposure so brightness can be compared across the series):

- fig4_3_homogeneous_albedo.pvsm   uniform dust (density 0.02), tau 128, star at the centre
                                   (20 000 K, bump radius 0.01)       -- thesis Fig. 4.3
- fig4_4_nebula_offset_a.pvsm      turbulence, scale 0.15, tau 128, noise offset (0.5, 0.5, 0.5)
- fig4_5_nebula_offset_b.pvsm      the same with noise offset (3.5, 1.5, 0.5)  -- Figs. 4.4/4.5

One for an adaptive density:

- adaptive_cloud.pvsm              a clumpy cloud as a hyper tree grid (examples/data/clumpy_cloud.htg,
                                   written here: three Gaussian clumps on 64^3 voxels, 2^3 blocks
                                   within 10 % merged) opened by ParaView's .htg reader into Nebula
                                   Light Field (Resolution 48^3, its leaves traced) and Nebula
                                   Colour, shown as an rgba volume with its star. Its FileName is
                                   relative to the repository, as fit_result's.

Two for polarization:

- polarized_nebula.pvsm            turbulent dust around a central star scattering by White's
                                   approximation (Nebula Light Field's Polarization), its sky image
                                   traced with Method peel-off, and Nebula Polarization Vectors over
                                   it in the sky view: the centrosymmetric pattern about the star.
- mie_nebula.pvsm                  the same with Mie grains (MRN astronomical silicate: the Grain
                                   properties), whose sky image holds Stokes V too.

And one for a fit's result:

- fit_result.pvsm                  the worked example's fit (examples/observations/fit-result.json,
                                   ``nebula-rt fit`` of the NGC 7023-like scene to the synthetic
                                   colour and ratio tables, docs/observations.md) opened by the
                                   plugin's reader into a Python View: the parameters with
                                   their errors first, one chart per observable kind with error
                                   bars (nebula_rt_paraview.fit_view). Its FileName is relative
                                   to the repository: load it with the data directory set to the
                                   repository (File > Load State, "Search files under specified
                                   directory"; ``load_state_safely(..., data_directory=REPO)``).

The defaults (48^3 voxels, 200 000 packets per band) load and render in about 11 s on two
CPU cores; the thesis used 128^3 voxels and 2.1 million packets (--grid 128 --photons 2100000,
or change GridShape / Photons in ParaView after loading: the properties panel of the dust
source and of each light field). The states leave Device empty and Backend "auto": a GPU is
used where there is one, else the CPU OpenCL device.

The shared exposure is the automatic exposure of the albedo-0.8 branch (the brightest),
measured while generating; the Exposure property of each Nebula Colour holds it. The colours'
opacity is the dust's own (Auto Opacity off, Opacity Scale 1), as in the thesis.

What a plain ``LoadState`` (or File > Load State) gets from the file itself:

- one tab (layout) with one render view, in preview mode at the figure's size (the layout's
  PreviewMode): the GUI keeps the figure's aspect ratio, so all four panels fit whatever the
  window; the stored camera (with the plugin loaded, ``LoadState(...); Render()`` keeps it);
- labels made from the data: a Python Annotation on each light field prints its albedo from
  the field data (``band_albedo``), and one on the first prints the title with its tau, so an
  edit of Albedo or Tau shows in the labels.
"""

from __future__ import annotations

import argparse
import os
import sys

from paraview import simple

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "plugin"))
from nebula_rt_paraview.view import load_plugin, show_rgba_volume, show_stars  # noqa: E402

ALBEDOS = (0.2, 0.4, 0.6, 0.8)
STAR = [0.5, 0.5, 0.5, 1.0, 20000.0, 0.01]
#: gap between the volumes of the series (box units)
PITCH = 1.25
#: the figure's size in pixels (the layout's preview size, the screenshots')
SIZE = [1600, 540]

FIGURES = {
    "fig4_3_homogeneous_albedo": dict(
        title="Homogeneous dust, tau %g: albedo series (thesis Fig. 4.3)",
        density=dict(Model="uniform", UniformDensity=0.02),
    ),
    "fig4_4_nebula_offset_a": dict(
        title="Nebula, noise offset (0.5, 0.5, 0.5), tau %g: albedo series (thesis Fig. 4.4)",
        density=dict(Model="turbulence", Scale=0.15, Offset=[0.5, 0.5, 0.5]),
    ),
    "fig4_5_nebula_offset_b": dict(
        title="Nebula, noise offset (3.5, 1.5, 0.5), tau %g: albedo series (thesis Fig. 4.5)",
        density=dict(Model="turbulence", Scale=0.15, Offset=[3.5, 1.5, 0.5]),
    ),
}

#: the Python Annotation expressions of the labels (field data of a light field: band_albedo,
#: tau); "%g" keeps 0.2 as 0.2
ALBEDO_LABEL = '"albedo %g" % band_albedo[0]'


def title_expression(title):
    return repr(title) + " % tau[0]"


def reset_session():
    for px in reversed(list(simple.GetSources().values())):  # consumers first
        simple.Delete(px)
    for view in list(simple.GetViews()):
        simple.Delete(view)
    for layout in list(simple.GetLayouts().values()):
        simple.RemoveLayout(layout)


def new_view(name, size):
    """A fresh session's render view in its own tab ``name``, at the figure's ``size`` (the
    GUI shows the layout at this aspect ratio, scaled to fit), black, without axes."""
    reset_session()
    view = simple.CreateView("RenderView")
    layout = simple.GetLayout(view) or simple.CreateLayout(name)
    if simple.GetLayout(view) is None:
        simple.AssignViewToLayout(view=view, layout=layout, hint=0)
    simple.RenameLayout(name, layout)
    layout.PreviewMode = size
    view.ViewSize = size
    view.OrientationAxesVisibility = 0
    if "UseColorPaletteForBackground" in view.ListProperties():
        view.UseColorPaletteForBackground = 0
    view.Background = [0.0, 0.0, 0.0]
    return view, layout


def build(name, spec, grid, photons, tau, device):
    """The pipeline and view of one figure; returns (view, colour proxies)."""
    view, layout = new_view(name, SIZE)

    dust = simple.NebulaDustDensity(registrationName="Dust density", GridShape=[grid] * 3, Stars=STAR,
                                    Device=device, **spec["density"])
    colours, lights = [], []
    for i, albedo in enumerate(ALBEDOS):
        # the input positionally: paraview.simple picks the DensityArray default from it
        light = simple.NebulaLightField(dust, registrationName=f"Light field, albedo {albedo}")
        light.DensityArray = ["POINTS", "density"]
        light.Stars = STAR
        light.Tau = tau
        light.Photons = photons
        light.BandPreset = "thesis-rgb"
        light.OverrideOptics = 1
        light.Albedo = albedo
        light.G = 0.6
        light.Seed = 1 + i
        light.Device = device
        colour = simple.NebulaColour(light, registrationName=f"Colour, albedo {albedo}")
        # the thesis's figures show the dust's own opacity (Opacity Scale 1), not the auto
        # opacity of a new Nebula Colour: the homogeneous box's optical depth is the point
        colour.AutoOpacity = 0
        colour.OpacityScale = 1.0
        display = show_rgba_volume(colour, view)
        display.Position = [i * PITCH, 0.0, 0.0]
        stars = show_stars(light, view)
        stars.Position = [i * PITCH, 0.0, 0.0]
        colours.append(colour)
        lights.append(light)

        # label under the cube, anchored in the scene (follows the camera), from the data
        label = simple.PythonAnnotation(registrationName=f"Label, albedo {albedo}", Input=light,
                                        ArrayAssociation="Field Data", Expression=ALBEDO_LABEL)
        ld = simple.Show(label, view)
        ld.TextPropMode = "Billboard 3D Text"
        ld.BillboardPosition = [i * PITCH + 0.38, -0.1, 0.5]
        ld.FontSize = 15
        ld.Color = [0.8, 0.8, 0.8]
    title = simple.PythonAnnotation(registrationName="Title", Input=lights[0], ArrayAssociation="Field Data",
                                    Expression=title_expression(spec["title"]))
    td = simple.Show(title, view)
    td.WindowLocation = "Upper Center"
    td.FontSize = 14
    td.Color = [0.8, 0.8, 0.8]

    # one exposure for the whole series: the automatic one of the brightest branch
    colours[-1].UpdatePipeline()
    exposure = float(colours[-1].FieldData["exposure"].GetRange(0)[0])
    for c in colours:
        c.AutoExposure = 0
        c.Exposure = exposure

    # camera: look down -z at the row of cubes (box units), parallel projection (render once
    # first: paraview.simple resets the camera on a session's first render)
    simple.Render(view)
    width = (len(ALBEDOS) - 1) * PITCH + 1.0
    view.CameraParallelProjection = 1
    view.CameraFocalPoint = [0.5 * width, 0.42, 0.5]
    view.CameraPosition = [0.5 * width, 0.42, 6.0]
    view.CameraViewUp = [0.0, 1.0, 0.0]
    view.CameraParallelScale = 0.87
    # only this figure's tab (CreateView may have made one before CreateLayout)
    for other in list(simple.GetLayouts().values()):
        if other is not layout:
            simple.RemoveLayout(other)
    simple.SetActiveView(view)
    simple.SetActiveSource(colours[0])
    return view, colours


FIT_RESULT = os.path.join("examples", "observations", "fit-result.json")
FIT_SIZE = [900, 900]


def build_fit_result():
    """The fit result's layout: its reader's two ports in a Python View (nebula_rt_paraview.fit_view).
    The reader's FileName is stored relative to the repository (made from there)."""
    from nebula_rt_paraview.view import show_fit_result

    reset_session()
    reader = simple.NebulaFitResultReader(registrationName="fit-result.json", FileName=FIT_RESULT)
    view = simple.CreateView("PythonView")
    simple.AssignViewToLayout(view)
    simple.GetLayout(view).PreviewMode = FIT_SIZE
    show_fit_result(reader, view)
    return view, reader


ADAPTIVE_DATA = os.path.join("examples", "data", "clumpy_cloud.htg")
ADAPTIVE_SIZE = [700, 700]


def write_clumpy_cloud(path):
    """The adaptive example's density (the notebook examples/notebooks/adaptive_densities.ipynb
    makes the same cloud): three Gaussian clumps on a thin background, 64^3 voxels merged into
    an octree where 2^3 blocks agree within 10 %, written as a .htg."""
    import numpy as np
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridWriter

    from nebula_rt.density import coarsen
    from nebula_rt.filters.adaptive import octree_to_htg

    n = 64
    x = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    rho = np.full((n, n, n), 0.5)
    for (cx, cy, cz), w, amp in (((0.35, 0.55, 0.5), 0.06, 40.0), ((0.65, 0.4, 0.55), 0.04, 60.0),
                                 ((0.5, 0.7, 0.35), 0.08, 20.0)):
        rho += amp * np.exp(-((X - cx) ** 2 + (Y - cy) ** 2 + (Z - cz) ** 2) / (2 * w * w))
    tree = coarsen(rho, (4, 4, 4), tolerance=0.1)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    writer = vtkXMLHyperTreeGridWriter()
    writer.SetInputData(octree_to_htg(tree, {"density": tree.density}))
    writer.SetFileName(path)
    if writer.Write() != 1:
        raise SystemExit(f"could not write {path}")
    return tree


def build_adaptive(photons, device):
    """The adaptive example's pipeline: the .htg (FileName relative to the repository, made
    from there) -> Nebula Light Field (Resolution 48^3) -> Nebula Colour, an rgba volume with
    its star, looked at down -z."""
    view, layout = new_view("adaptive_cloud", ADAPTIVE_SIZE)
    cloud = simple.OpenDataFile(ADAPTIVE_DATA, registrationName="clumpy_cloud.htg")
    light = simple.NebulaLightField(cloud, registrationName="Light field (adaptive)")
    light.DensityArray = ["CELLS", "density"]
    light.Resolution = [48, 48, 48]
    light.Stars = [0.5, 0.5, 0.5, 1.0, 15000.0, 0.0]
    light.Tau = 4.0
    light.Photons = photons
    light.Device = device
    colour = simple.NebulaColour(light, registrationName="Colour (adaptive)")
    show_rgba_volume(colour, view)
    show_stars(light, view)
    simple.Render(view)
    view.CameraParallelProjection = 1
    view.CameraFocalPoint = [0.5, 0.5, 0.5]
    view.CameraPosition = [0.5, 0.5, 6.0]
    view.CameraViewUp = [0.0, 1.0, 0.0]
    view.CameraParallelScale = 0.6
    for other in list(simple.GetLayouts().values()):
        if other is not layout:
            simple.RemoveLayout(other)
    simple.SetActiveView(view)
    simple.SetActiveSource(colour)
    return view, light, colour


POLARIZED_SIZE = [700, 700]


#: the polarized states' scattering: White's approximation, and Mie grains (MRN astronomical silicate)
POLARIZED_OPTICS = {"polarized_nebula": dict(Polarization="white", PeakPolarization=0.5),
                    "mie_nebula": dict(Polarization="mie", GrainMaterial="astronomical-silicate",
                                       GrainRadiusMin=0.005, GrainRadiusMax=0.25, GrainSizeSlope=3.5)}


def build_polarized(photons, device, name="polarized_nebula"):
    """The polarized nebula: turbulent dust (48^3, the thesis's noise, tau 6) around a central
    15 000 K star, scattering by White's approximation (p_l 0.5) or (``mie_nebula``) by Mie
    grains -> Nebula Sky Image (peel-off, 96^2 pixels over the box; Mie grains add V) -> Nebula
    Polarization Vectors (blocks of 6 pixels, P >= 3 errors), the picture and its vectors in the
    sky image's own view."""
    reset_session()
    star = [0.5, 0.5, 0.5, 1.0, 15000.0, 0.0]
    dust = simple.NebulaDustDensity(registrationName="Dust (polarized)", GridShape=[48, 48, 48], Stars=star,
                                    Device=device)
    light = simple.NebulaLightField(dust, registrationName="Light field (polarized)", Tau=6.0,
                                    Photons=photons, Device=device, **POLARIZED_OPTICS[name])
    light.DensityArray = ["POINTS", "density"]
    sky = simple.NebulaSkyImage(light, registrationName="Sky image (peel-off)", ImageSize=[96, 96], Extent=1.0,
                                Method="peel-off")
    vectors = simple.NebulaPolarizationVectors(sky, registrationName="Polarization vectors", BlockSize=6,
                                               MinSignalToNoise=3.0, VectorScale=1.5)
    view = simple.CreateView("NebulaSkyView")
    simple.AssignViewToLayout(view)
    layout = simple.GetLayout(view)
    simple.RenameLayout(name, layout)
    layout.PreviewMode = POLARIZED_SIZE
    view.ViewSize = POLARIZED_SIZE
    simple.Show(sky, view)
    simple.Show(vectors, view)
    simple.Render(view)
    for other in list(simple.GetLayouts().values()):
        if other is not layout:
            simple.RemoveLayout(other)
    simple.SetActiveView(view)
    simple.SetActiveSource(vectors)
    return view, (light, sky, vectors)


def save_state(view, name, size, out, screenshots=None):
    """Write ``out``/``name``.pvsm and, with ``screenshots``, paraview-``name``.png there at
    ``size`` (the folders taken as given, made absolute first: the caller may have changed
    directory to the repository)."""
    path = os.path.join(os.path.abspath(out), f"{name}.pvsm")
    simple.SaveState(path)
    print(f"wrote {path}")
    if screenshots:
        png = os.path.join(os.path.abspath(screenshots), f"paraview-{name}.png")
        os.makedirs(os.path.dirname(png), exist_ok=True)
        simple.SaveScreenshot(png, view, ImageResolution=size)
        print(f"wrote {png}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grid", type=int, default=48, help="voxels per axis (default 48; thesis 128)")
    ap.add_argument("--photons", type=int, default=200_000, help="packets per band (default 2e5; thesis 2.1e6)")
    ap.add_argument("--tau", type=float, default=128.0, help="optical depth across the box at density 1")
    ap.add_argument("--out", default=HERE, help="folder for the .pvsm files (default: state_files/)")
    ap.add_argument("--only", nargs="*", default=None, help="figure names to make (default: all)")
    ap.add_argument("--device", default="", help="Device property stored in the states (default: empty = auto)")
    ap.add_argument("--screenshots", default=None, help="also save paraview-<figure>.png into this folder")
    args = ap.parse_args(argv)

    load_plugin()
    os.makedirs(args.out, exist_ok=True)
    if not args.only or "adaptive_cloud" in args.only:
        cwd = os.getcwd()
        os.chdir(os.path.dirname(HERE))  # (the reader's relative FileName)
        try:
            write_clumpy_cloud(ADAPTIVE_DATA)
            view, light, colour = build_adaptive(args.photons, args.device)
            simple.Render(view)
            if colour.GetClientSideObject().last_error or light.GetClientSideObject().last_error:
                raise SystemExit(f"adaptive_cloud: {light.GetClientSideObject().last_error}")
            save_state(view, "adaptive_cloud", ADAPTIVE_SIZE, os.path.join(cwd, args.out),
                       args.screenshots and os.path.join(cwd, args.screenshots))
        finally:
            os.chdir(cwd)
    if not args.only or "fit_result" in args.only:
        cwd = os.getcwd()
        os.chdir(os.path.dirname(HERE))  # (the reader's relative FileName)
        try:
            view, reader = build_fit_result()
            simple.Render(view)
            if reader.GetClientSideObject().last_error:
                raise SystemExit(f"fit_result: {reader.GetClientSideObject().last_error}")
            save_state(view, "fit_result", FIT_SIZE, os.path.join(cwd, args.out),
                       args.screenshots and os.path.join(cwd, args.screenshots))
        finally:
            os.chdir(cwd)
    for name in POLARIZED_OPTICS:
        if args.only and name not in args.only:
            continue
        view, algs = build_polarized(args.photons, args.device, name)
        simple.Render(view)
        errors = [a.GetClientSideObject().last_error for a in algs]
        if any(errors):
            raise SystemExit(f"{name}: {errors}")
        save_state(view, name, POLARIZED_SIZE, args.out, args.screenshots)
    for name, spec in FIGURES.items():
        if args.only and name not in args.only:
            continue
        view, colours = build(name, spec, args.grid, args.photons, args.tau, args.device)
        simple.Render(view)
        errors = [c.GetClientSideObject().last_error for c in colours]
        if any(errors):
            raise SystemExit(f"{name}: {errors}")
        path = os.path.join(args.out, name + ".pvsm")
        simple.SaveState(path)
        print(f"wrote {path} (exposure {colours[0].Exposure[0] if hasattr(colours[0].Exposure, '__len__') else colours[0].Exposure:.4g})")
        if args.screenshots:
            os.makedirs(args.screenshots, exist_ok=True)
            png = os.path.join(args.screenshots, f"paraview-{name}.png")
            simple.SaveScreenshot(png, view, ImageResolution=SIZE)
            print(f"wrote {png}")


if __name__ == "__main__":
    main()
