"""Adaptive densities in and out of VTK (nebula_rt.filters.adaptive) with the VTK of the
library's environment: an octree written as a vtkHyperTreeGrid (and through an .htg file)
comes back as the same field; what the transport cannot take is refused by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nebula_rt.density.octree import coarsen
from nebula_rt.density.resample import box_averages
from nebula_rt.filters.adaptive import octree_from_amr, octree_from_htg, octree_to_htg


def clumpy(n=16):
    x = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(x, x, x, indexing="ij")
    rho = np.ones((n, n, n))
    rho += 30.0 * np.exp(-((X - 0.3) ** 2 + (Y - 0.6) ** 2 + (Z - 0.4) ** 2) / 0.004)
    return np.round(rho, 1)  # equal values in the background: they merge


def _same_field(a, b, shape):
    la, ha, va = a.leaves()
    lb, hb, vb = b.leaves()
    assert a.n_leaves == b.n_leaves and a.depth() == b.depth() and a.roots == b.roots
    np.testing.assert_array_equal(box_averages(la, ha, va, shape), box_averages(lb, hb, vb, shape))


def test_an_octree_goes_through_a_hyper_tree_grid_and_an_htg_file(tmp_path):
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridReader, vtkXMLHyperTreeGridWriter

    tree = coarsen(clumpy()[:, 4:12, :], (2, 1, 2))  # root cells of 8^3 voxels
    assert 16 < tree.n_leaves < 16 * 8 * 16 and tree.depth() == 3
    htg = octree_to_htg(tree, {"density": tree.density}, bounds=(0.0, 2.0, -1.0, 0.0, 5.0, 7.0))
    assert htg.GetNumberOfLeaves() == tree.n_leaves
    _same_field(octree_from_htg(htg), tree, (16, 8, 16))
    path = tmp_path / "tree.htg"
    writer = vtkXMLHyperTreeGridWriter()
    writer.SetInputData(htg)
    writer.SetFileName(str(path))
    assert writer.Write() == 1
    reader = vtkXMLHyperTreeGridReader()
    reader.SetFileName(str(path))
    reader.Update()
    _same_field(octree_from_htg(reader.GetOutput()), tree, (16, 8, 16))


def test_refined_cells_hold_their_childrens_mean():
    from vtkmodules.util.numpy_support import vtk_to_numpy

    tree = coarsen(clumpy(8), (1, 1, 1))
    htg = octree_to_htg(tree, {"density": tree.density})
    values = vtk_to_numpy(htg.GetCellData().GetArray("density"))
    assert values.size == htg.GetNumberOfCells() == len(tree.child)
    lo, hi, v = tree.leaves()
    root_mean = (v * np.prod(hi - lo, axis=1)).sum()
    assert np.isclose(values.max(), v.max()) and any(np.isclose(values, root_mean, rtol=1e-6))


def test_what_the_transport_cannot_take_is_refused():
    from vtkmodules.vtkCommonCore import vtkBitArray

    tree = coarsen(clumpy(8), (1, 1, 1))
    with pytest.raises(ValueError, match="no cell array 'rho'.*density"):
        octree_from_htg(octree_to_htg(tree, {"density": tree.density}), "rho")
    htg = octree_to_htg(tree, {"density": tree.density})
    mask = vtkBitArray()
    mask.SetNumberOfTuples(htg.GetNumberOfCells())
    mask.Fill(0)
    mask.SetValue(htg.GetNumberOfCells() - 1, 1)  # hide one leaf
    htg.SetMask(mask)
    with pytest.raises(ValueError, match="holes"):
        octree_from_htg(htg)
    bad = tree.density.copy()
    bad[3] = -2.0
    with pytest.raises(ValueError, match="density -2.0 must be finite and >= 0"):
        octree_from_htg(octree_to_htg(tree, {"density": bad}))
    with pytest.raises(ValueError, match="values for"):
        octree_to_htg(tree, {"density": tree.density[:-1]})


def _amr(ratio=2, level0=(((0, 0, 0), (7, 7, 7)),), fine=((4, 4, 4), (11, 11, 11)), with_array=True):
    """Two levels over the unit box: level 0 of 8^3 cells, level 1 refining level-0 cells
    [2, 5]^3 (level-1 cells [4, 11]^3 at ratio 2); each cell's density a function of its centre."""
    from vtkmodules import vtkCommonDataModel as dm
    from vtkmodules.util.numpy_support import numpy_to_vtk

    def block(lo, hi, h):
        n = np.array(hi) - np.array(lo) + 1
        g = dm.vtkUniformGrid()
        g.SetOrigin(*(np.array(lo) * h))
        g.SetSpacing(h, h, h)
        g.SetDimensions(*(n + 1))
        ijk = np.stack(np.unravel_index(np.arange(n.prod()), tuple(n), order="F"), axis=1) + lo
        if with_array:
            a = numpy_to_vtk(density_at((ijk + 0.5) * h), deep=1)
            a.SetName("density")
            g.GetCellData().AddArray(a)
        return g

    amr = dm.vtkOverlappingAMR()
    if hasattr(dm, "vtkOverlappingAMRMetaData"):
        amr.Initialize([len(level0), 1])
    else:
        amr.Initialize(2, [len(level0), 1])
    h0 = 1.0 / 8
    amr.SetOrigin([0.0, 0.0, 0.0])
    amr.SetSpacing(0, [h0] * 3)
    amr.SetSpacing(1, [h0 / ratio] * 3)
    amr.SetRefinementRatio(0, ratio)
    for i, (lo, hi) in enumerate(level0):
        amr.SetAMRBox(0, i, dm.vtkAMRBox(list(lo), list(hi)))
        amr.SetDataSet(0, i, block(lo, hi, h0))
    amr.SetAMRBox(1, 0, dm.vtkAMRBox(list(fine[0]), list(fine[1])))
    amr.SetDataSet(1, 0, block(fine[0], fine[1], h0 / ratio))
    return amr


def density_at(c):
    return 1.0 + np.exp(-np.sum((c - 0.45) ** 2, axis=1) / 0.01)


def test_an_amr_hierarchy_is_the_octree_of_its_visible_cells():
    tree = octree_from_amr(_amr())
    assert tree.roots == (8, 8, 8) and tree.depth() == 1
    assert tree.n_leaves == 8 ** 3 - 4 ** 3 + 8 ** 3  # level 0 less the 64 cells level 1 covers, plus level 1
    lo, hi, v = tree.leaves()
    got = box_averages(lo, hi, v, (16, 16, 16))
    # each 1/16 voxel lies in one level-1 cell (inside [0.25, 0.75)^3) or one level-0 cell
    centres = (np.array(list(np.ndindex(16, 16, 16))) + 0.5) / 16
    fine = np.all((centres >= 0.25) & (centres < 0.75), axis=1)
    want = np.where(fine, density_at(centres), density_at((np.floor(centres * 8) + 0.5) / 8))
    np.testing.assert_allclose(got.reshape(-1), want.astype(np.float32), rtol=1e-6)


def test_what_an_octree_cannot_hold_is_refused():
    with pytest.raises(ValueError, match="refines by 3"):
        octree_from_amr(_amr(ratio=3, fine=((6, 6, 6), (11, 11, 11))))
    with pytest.raises(ValueError, match="no one-component cell array 'density'"):
        octree_from_amr(_amr(with_array=False))
    with pytest.raises(ValueError, match="holes"):  # level 0's two blocks leave a gap at i = 4
        octree_from_amr(_amr(level0=(((0, 0, 0), (3, 7, 7)), ((5, 0, 0), (7, 7, 7)))))
    assert octree_from_amr(_amr(level0=(((0, 0, 0), (3, 7, 7)), ((4, 0, 0), (7, 7, 7))))).n_leaves == 960


def test_the_light_on_a_tree_goes_to_paraview_and_onto_a_grid(backend):
    """J per leaf as cell data of a vtkHyperTreeGrid (a refined cell holds its children's
    mean) and, by exact overlap volume, on a uniform grid: for a tree of a grid's voxels that
    grid's J (the energy sum J x volume kept whatever grid is chosen)."""
    from conftest import centre_star, one_band
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from nebula_rt.transport import trace

    rho = (np.random.default_rng(8).random((8, 8, 8)) + 0.2).astype(np.float32)
    tree = coarsen(rho, (1, 1, 1))
    kw = dict(tau=3.0, photons=10_000, seed=6)
    tl = trace(tree, one_band(0.6, 0.5), centre_star(), backend=backend, method="analog", **kw)
    grid = trace(rho, one_band(0.6, 0.5), centre_star(), backend=backend, method="analog", batch_size=10_000, **kw)
    htg = octree_to_htg(tree, {"J_V": tl.J[0], "density": tree.density})
    j_cells = vtk_to_numpy(htg.GetCellData().GetArray("J_V"))
    assert htg.GetNumberOfLeaves() == tree.n_leaves and j_cells.max() == pytest.approx(tl.J[0].max())
    lo, hi, _ = tree.leaves()
    np.testing.assert_allclose(box_averages(lo, hi, tl.J[0], (8, 8, 8)), grid.J[0], rtol=1e-5)
    coarse = box_averages(lo, hi, tl.J[0], (4, 4, 4))
    assert coarse.sum() / 64 == pytest.approx(grid.J[0].sum() / 512, rel=1e-6)


def _write_htg(tree, path):
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridWriter

    writer = vtkXMLHyperTreeGridWriter()
    writer.SetInputData(octree_to_htg(tree, {"density": tree.density}))
    writer.SetFileName(str(path))
    assert writer.Write() == 1
    return path


def _adaptive_scene(path, shape=16, **overrides):
    from conftest import TEST_BACKEND, TEST_DEVICE

    from nebula_rt.scene import Scene

    sets = [f"grid.shape=[{shape},{shape},{shape}]", 'dust.model="file"', f'dust.file="{path}"', "dust.tau=8.0",
            "dust.floor=0.0", "stars[0].bump_radius=0.0", "transport.photons=20000", 'transport.method="analog"',
            f'transport.device="{TEST_DEVICE}"', f'transport.backend="{TEST_BACKEND}"']
    return Scene.load("examples/scenes/thesis-default.toml").with_overrides(
        sets + [f"{k}={v}" for k, v in overrides.items()])


def test_a_scene_traces_an_htg_density_and_writes_the_grid_it_asks_for(tmp_path):
    """dust.file an .htg: the pipeline reads it as an octree, traces its leaves and writes
    the light field on grid.shape (a .vti of the output contract). Against the same density as
    a .npy on the grid: the density comes back voxel for voxel (a merged leaf holds equal
    voxels), the packets' fates agree (a few of 20,000 per band part at float32 face
    crossings) and the light's total, sum of J over the voxels, agrees to 1e-3 (J per leaf is
    the leaf's average, the grid's per voxel: their sums are the same track length)."""
    from nebula_rt.filters.vti import read_vti, write_vti
    from nebula_rt.pipeline import Pipeline

    rho = clumpy().astype(np.float32)
    tree = coarsen(rho, (2, 2, 2))
    assert tree.n_leaves < rho.size / 2  # the background merged
    htg = _write_htg(tree, tmp_path / "cloud.htg")
    np.save(tmp_path / "cloud.npy", rho)
    pipeline = Pipeline()
    light = pipeline.run(_adaptive_scene(htg))
    read = pipeline.density(_adaptive_scene(htg))  # the octree as read (its leaves' numbering)
    assert read.n_leaves == tree.n_leaves
    grid = Pipeline().run(_adaptive_scene(tmp_path / "cloud.npy"))
    assert light.J.shape == grid.J.shape == (3, 16, 16, 16)
    np.testing.assert_allclose(light.density, rho, rtol=1e-6)
    assert light.transport.J.shape == (3, tree.n_leaves)
    c_tree, c_grid = light.transport.counts, grid.transport.counts
    assert np.all(c_tree[:, 0] == 20_000) and np.abs(c_tree - c_grid).max() <= 10, (c_tree, c_grid)
    np.testing.assert_allclose(light.J.sum(axis=(1, 2, 3)), grid.J.sum(axis=(1, 2, 3)), rtol=1e-3)
    assert light.rgba is not None and light.rgba.shape == (16, 16, 16, 4)
    path = write_vti(tmp_path / "out.vti", light.point_arrays(), light.field_data(), light.spacing, light.origin)
    arrays, fd, *_ = read_vti(path)
    np.testing.assert_array_equal(arrays["density"], light.density)
    # where one leaf covers a voxel, the voxel keeps the leaf's relative error
    lo, hi, _ = read.leaves()
    big = np.argmax(np.prod(hi - lo, axis=1))
    i = np.floor(lo[big] * 16 + 1e-9).astype(int)
    assert light.rel_error[1][tuple(i)] == pytest.approx(light.transport.rel_error[1][big], rel=1e-6)


def test_a_star_bump_on_a_tree_is_the_bump_on_its_grid(tmp_path):
    """A star's bump (stars[i].bump_radius) added to an adaptive density: on a tree whose
    leaves are a grid's voxels the leaves get the voxels' bump averages (the device's kernel
    on the grid, float32, against the leaves' float64 averages), and the bump's mass is kept."""
    from conftest import TEST_BACKEND, TEST_DEVICE

    from nebula_rt.density import generate_density, load_tree

    rho = (np.random.default_rng(1).random((16, 16, 16)) + 1.0).astype(np.float32)  # no two equal: no merging
    htg = _write_htg(coarsen(rho, (2, 2, 2)), tmp_path / "cloud.htg")
    np.save(tmp_path / "cloud.npy", rho)
    bump = {"stars[0].bump_radius": 0.1, "stars[0].position": "[0.47,0.52,0.5]"}
    tree = load_tree(_adaptive_scene(htg, **bump))
    from nebula_rt.backends import get_backend

    grid = generate_density(_adaptive_scene(tmp_path / "cloud.npy", **bump), get_backend(TEST_BACKEND, TEST_DEVICE))
    lo, hi, v = tree.leaves()
    on_grid = box_averages(lo, hi, v, (16, 16, 16))
    np.testing.assert_allclose(on_grid, grid, rtol=2e-6)
    # the bump's mass, 4 pi r^3 int_0^1 (1 - u^2)^3 u^2 du = 4 pi r^3 16 / 315, in voxel sums
    mass = 4 * np.pi * 0.1**3 * 16 / 315 * 16**3
    assert (on_grid.sum() - rho.astype(np.float64).sum()) == pytest.approx(mass, rel=1e-2)


def test_a_scene_traces_an_amr_density(tmp_path):
    """dust.file a .vthb (VTK's overlapping AMR): its visible cells become the leaves; the run
    gives J everywhere the packets reach, on the output grid."""
    from vtkmodules.vtkIOXML import vtkXMLUniformGridAMRWriter

    from nebula_rt.pipeline import Pipeline

    writer = vtkXMLUniformGridAMRWriter()
    writer.SetInputData(_amr())
    writer.SetFileName(str(tmp_path / "cloud.vthb"))
    assert writer.Write() == 1
    light = Pipeline().run(_adaptive_scene(tmp_path / "cloud.vthb", shape=8, **{"dust.tau": 2.0}))
    assert light.transport.J.shape == (3, 8 ** 3 - 4 ** 3 + 8 ** 3)
    assert light.J.shape == (3, 8, 8, 8) and np.all(np.isfinite(light.J)) and light.J.min() > 0
    # the density on the output grid: each 1/8 voxel is one level-0 cell or the mean of 8 level-1 cells
    centres = (np.array(list(np.ndindex(8, 8, 8))) + 0.5) / 8
    coarse = ~np.all((centres >= 0.25) & (centres < 0.75), axis=1)
    np.testing.assert_allclose(light.density.reshape(-1)[coarse], density_at(centres[coarse]), rtol=1e-6)


def test_what_an_adaptive_scene_cannot_do_is_refused_by_name(tmp_path):
    from nebula_rt.density import generate_density
    from nebula_rt.errors import SceneError
    from nebula_rt.pipeline import Pipeline

    tree = coarsen(clumpy(8), (1, 1, 1))
    htg = _write_htg(tree, tmp_path / "cloud.htg")
    with pytest.raises(SceneError) as e:
        Pipeline().run(_adaptive_scene(htg, **{"transport.estimator": '"collision-filter"'}))
    assert e.value.parameter == "transport.estimator"
    with pytest.raises(SceneError) as e:  # what needs a grid says so
        generate_density(_adaptive_scene(htg), None)
    assert e.value.parameter == "dust.file" and "uniform grid" in str(e.value)
    bad = tmp_path / "broken.htg"
    bad.write_bytes(b"<VTKFile type='HyperTreeGrid'> not a tree")
    with pytest.raises(SceneError) as e:
        Pipeline().run(_adaptive_scene(bad))
    assert e.value.parameter == "dust.file" and "adaptive density" in str(e.value)
    with pytest.raises(SceneError) as e:
        Pipeline().run(_adaptive_scene(htg, **{"dust.array": '"rho"'}))
    assert e.value.parameter == "dust.file" and "rho" in str(e.value)


def test_the_light_field_filter_traces_an_adaptive_input_as_the_image_it_resolves(tmp_path):
    """Nebula Light Field with a vtkHyperTreeGrid input whose leaves are a grid's voxels (all
    values differ: nothing merges), against the same density as a vtkImageData cell array:
    port 0 on Resolution = the grid has the image's geometry, the same packet counts and J to
    float32 rounding of the two walks' faces; an AMR input runs too; a bad Resolution and a
    missing array are refused by name with an empty output."""
    from vtkmodules.util.numpy_support import numpy_to_vtk, vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkImageData

    from nebula_rt.filters import NebulaLightField

    n = 8
    rho = (np.random.default_rng(4).random((n, n, n)) + 0.5).astype(np.float32)
    tree = coarsen(rho, (1, 1, 1))
    assert tree.n_leaves == n**3
    htg = octree_to_htg(tree, {"density": tree.density}, bounds=(0.0, 2.0, 0.0, 2.0, 0.0, 2.0))
    img = vtkImageData()
    img.SetDimensions(n + 1, n + 1, n + 1)
    img.SetSpacing(0.25, 0.25, 0.25)
    arr = numpy_to_vtk(np.ravel(rho, order="F"), deep=1)
    arr.SetName("density")
    img.GetCellData().AddArray(arr)

    def run(inp, cells=False, **props):
        f = NebulaLightField()
        f.SetInputDataObject(inp)
        if cells:
            f.SetInputArrayToProcess(0, 0, 0, 1, "density")  # the cell array
        f.SetPhotons(20000)
        f.SetTau(3.0)
        for k, v in props.items():
            getattr(f, "Set" + k)(*v) if isinstance(v, tuple) else getattr(f, "Set" + k)(v)
        f.Update()
        return f

    a = run(htg, Resolution=(n, n, n))
    b = run(img, cells=True)
    assert a.last_error is None and b.last_error is None, (a.last_error, b.last_error)
    oa, ob = a.GetOutputDataObject(0), b.GetOutputDataObject(0)
    assert oa.GetDimensions() == ob.GetDimensions() == (n, n, n)
    np.testing.assert_allclose(oa.GetSpacing(), ob.GetSpacing())
    np.testing.assert_allclose(oa.GetOrigin(), ob.GetOrigin())
    np.testing.assert_array_equal(a.last_light.transport.counts, b.last_light.transport.counts)
    for name in ("J_G", "density"):
        np.testing.assert_allclose(vtk_to_numpy(oa.GetPointData().GetArray(name)),
                                   vtk_to_numpy(ob.GetPointData().GetArray(name)), rtol=2e-5)
    inert = run(img, cells=True, Resolution=(4, 4, 4))  # an image keeps its grid, and says so
    assert inert.GetOutputDataObject(0).GetDimensions() == (n, n, n)
    assert any("Resolution" in str(w) for w in inert.last_warnings), inert.last_warnings
    c = run(_amr(), Resolution=(8, 8, 8))
    assert c.last_error is None and c.GetOutputDataObject(0).GetNumberOfPoints() == 512
    d = run(htg, Resolution=(0, 8, 8))
    assert "Resolution" in d.last_error and d.GetOutputDataObject(0).GetNumberOfPoints() == 0
    e = run(htg, DensityArrayName="rho")
    assert "no cell array 'rho'" in e.last_error


def _write_particles(path, points, masses, h, names=("mass", "smoothing_length")):
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkPolyData
    from vtkmodules.vtkIOXML import vtkXMLPolyDataWriter

    poly = vtkPolyData()
    pts = vtkPoints()
    pts.SetData(numpy_to_vtk(np.ascontiguousarray(points, np.float64), deep=1))
    poly.SetPoints(pts)
    for name, values in zip(names, (masses, h)):
        arr = numpy_to_vtk(np.ascontiguousarray(values, np.float64), deep=1)
        arr.SetName(name)
        poly.GetPointData().AddArray(arr)
    w = vtkXMLPolyDataWriter()
    w.SetInputData(poly)
    w.SetFileName(str(path))
    assert w.Write() == 1
    return path


def test_a_scene_deposits_a_particle_snapshot_on_a_tree_and_traces_it(tmp_path):
    """dust.file a .vtp SPH snapshot in pc (a box of 10 pc from (-5, -5, -5)): the particles are
    deposited on an octree refined by count (dust.leaf_particles, dust.tree_depth) with their
    mass kept (the light field's density, mass per box volume, averages to the total mass), the
    clump refined deepest, and the tree traced; a particle outside the box and a missing array
    are refused by name."""
    from nebula_rt.errors import SceneError
    from nebula_rt.pipeline import Pipeline

    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.uniform(-4.9, 4.9, (2000, 3)), rng.normal(1.0, 0.4, (3000, 3))])
    masses = rng.uniform(0.5, 1.5, len(pts)) * 1e-3
    h = np.full(len(pts), 0.3)
    snap = _write_particles(tmp_path / "snap.vtp", pts, masses, h)
    keys = {"grid.length": 10.0, "dust.particle_origin": "[-5.0,-5.0,-5.0]", "dust.leaf_particles": 16,
            "dust.tree_depth": 5, "dust.tau": 20.0}
    pipeline = Pipeline()
    scene = _adaptive_scene(snap, **keys)
    light = pipeline.run(scene)
    tree = pipeline.density(scene)
    assert 100 < tree.n_leaves and tree.depth() == 5
    lo, hi, rho = tree.leaves()
    np.testing.assert_allclose((rho.astype(np.float64) * np.prod(hi - lo, axis=1)).sum(), masses.sum(), rtol=1e-6)
    np.testing.assert_allclose(light.density.astype(np.float64).mean(), masses.sum(), rtol=1e-5)
    # the deepest leaves are where the clump is (1 pc from the centre: box (0.6, 0.6, 0.6))
    deep = np.prod(hi - lo, axis=1) == np.prod(hi - lo, axis=1).min()
    assert np.linalg.norm(0.5 * (lo + hi)[deep].mean(axis=0) - 0.6) < 0.1
    assert light.J.shape == (3, 16, 16, 16) and light.J.max() > 0 and light.transport.J.shape[1] == tree.n_leaves
    far = _write_particles(tmp_path / "far.vtp", np.concatenate([pts, [[6.0, 0.0, 0.0]]]), np.append(masses, 1e-3),
                           np.append(h, 0.3))
    with pytest.raises(SceneError) as e:
        Pipeline().run(_adaptive_scene(far, **keys))
    assert e.value.parameter == "dust.file" and "particle 5000" in str(e.value) and "outside" in str(e.value)
    with pytest.raises(SceneError) as e:
        Pipeline().run(_adaptive_scene(snap, **dict(keys, **{"dust.particle_mass": '"m"'})))
    assert e.value.parameter == "dust.file" and "'m'" in str(e.value)


def test_the_light_field_filter_takes_particles_and_gives_the_light_per_leaf(tmp_path):
    """Nebula Light Field with a vtkPolyData of SPH particles: deposited over the cube of the
    points' bounds as the scene path deposits a .vtp snapshot in the same box, so the same
    tree and the same packets' fates; port 2 holds the light per leaf as a vtkHyperTreeGrid
    over those bounds (J per leaf the run's, the density the tree's), empty for an image input;
    particles without their arrays are refused by name with empty outputs."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLPolyDataReader

    from nebula_rt.filters import NebulaLightField
    from nebula_rt.pipeline import Pipeline

    rng = np.random.default_rng(5)
    pts = np.concatenate([rng.normal(6.0, 1.0, (3000, 3)).clip(0.5, 9.5), [[0.0, 0.0, 0.0], [10.0, 10.0, 10.0]]])
    masses = rng.uniform(0.5, 1.5, len(pts)) * 1e-3
    h = np.full(len(pts), 0.4)
    snap = _write_particles(tmp_path / "snap.vtp", pts, masses, h)
    keys = {"grid.length": 10.0, "dust.leaf_particles": 16, "dust.tree_depth": 4, "dust.tau": 20.0,
            "transport.seed": 1}
    scene = _adaptive_scene(snap, **keys)
    pipeline = Pipeline()
    light = pipeline.run(scene)
    tree = pipeline.density(scene)
    reader = vtkXMLPolyDataReader()
    reader.SetFileName(str(snap))
    reader.Update()

    def run(inp, **props):
        f = NebulaLightField()
        f.SetInputDataObject(inp)
        for k, v in dict(Photons=20000, Tau=20.0, Method="analog", LeafParticles=16, TreeDepth=4, BoxLength=10.0,
                         Seed=1, Resolution=(16, 16, 16), **props).items():
            getattr(f, "Set" + k)(*v) if isinstance(v, tuple) else getattr(f, "Set" + k)(v)
        f.SetStars(0.5, 0.5, 0.5, 1.0, 20000.0, 0.0)
        f.Update()
        return f

    f = run(reader.GetOutput())
    assert f.last_error is None, f.last_error
    assert f.last_light.transport.J.shape[1] == tree.n_leaves
    np.testing.assert_array_equal(f.last_light.transport.counts, light.transport.counts)
    htg = f.GetOutputDataObject(2)
    assert htg.GetClassName() == "vtkHyperTreeGrid" and htg.GetNumberOfLeaves() == tree.n_leaves
    np.testing.assert_allclose(htg.GetBounds(), (0.0, 10.0) * 3, atol=1e-12)
    back = octree_from_htg(htg, "J_G")
    _, _, j = back.leaves()
    np.testing.assert_allclose(np.sort(j), np.sort(f.last_light.transport.J[1].astype(np.float32)), rtol=1e-6)
    _, _, d = octree_from_htg(htg, "density").leaves()
    np.testing.assert_allclose(np.sort(d), np.sort(tree.density), rtol=1e-6)
    mass = vtk_to_numpy(f.GetOutputDataObject(0).GetPointData().GetArray("density")).astype(np.float64).mean()
    np.testing.assert_allclose(mass, masses.sum(), rtol=1e-5)
    bad = run(reader.GetOutput(), ParticleMass="m")
    assert "Input" in bad.last_error and "'m'" in bad.last_error
    assert bad.GetOutputDataObject(0).GetNumberOfPoints() == 0 and bad.GetOutputDataObject(2).GetNumberOfLeaves() == 0
    img = run(_image_of(np.ones((4, 4, 4), np.float32)))
    assert img.last_error is None and img.GetOutputDataObject(2).GetNumberOfLeaves() == 0


def _image_of(rho):
    from vtkmodules.util.numpy_support import numpy_to_vtk
    from vtkmodules.vtkCommonDataModel import vtkImageData

    img = vtkImageData()
    img.SetDimensions(*rho.shape)
    arr = numpy_to_vtk(np.ravel(rho, order="F"), deep=1)
    arr.SetName("density")
    img.GetPointData().AddArray(arr)
    return img


def test_a_particle_snapshot_is_refined_by_optical_depth_with_dust_octree(tmp_path):
    """dust.octree with a .vtp snapshot: its cells are split by the particles' optical depth
    (dust.cell_tau, on the masses whose centres a cell holds) as well as by their count. A few
    heavy particles in a clump, too few for the count to split their cells: without it their
    leaves are coarse; with it every leaf above the deepest level holds an optical depth of at
    most cell_tau, the clump's leaves are finer, and the deposited mass is the particles'. An
    .htg with dust.octree is refused by name."""
    from nebula_rt.errors import SceneError
    from nebula_rt.pipeline import Pipeline
    from nebula_rt.transport.tree import leaf_edges

    rng = np.random.default_rng(9)
    pts = np.concatenate([rng.uniform(0.2, 9.8, (600, 3)), rng.normal(3.0, 0.3, (12, 3))])
    masses = np.concatenate([np.full(600, 1e-4), np.full(12, 0.05)])
    snap = _write_particles(tmp_path / "snap.vtp", pts, masses, np.full(len(pts), 0.3))
    keys = {"grid.length": 10.0, "dust.leaf_particles": 32, "dust.tree_depth": 6, "dust.tau": 40.0}
    plain = Pipeline().density(_adaptive_scene(snap, **keys))
    scene = _adaptive_scene(snap, **dict(keys, **{"dust.octree": "true", "dust.cell_tau": 0.5}))
    tree = Pipeline().density(scene)
    assert tree.n_leaves > plain.n_leaves
    # the criterion on the point masses, per leaf (their centres binned into the leaves)
    held = np.bincount(tree.locate(pts / 10.0), weights=masses, minlength=tree.n_leaves)
    edge = leaf_edges(tree)
    tau = 40.0 * held / edge**3 * edge
    coarse = edge > edge.min()
    assert np.all(tau[coarse] <= 0.5 * (1 + 1e-9)), tau[coarse].max()
    clump = tree.locate(np.array([[0.3, 0.3, 0.3]]))[0]
    assert edge[clump] < leaf_edges(plain)[plain.locate(np.array([[0.3, 0.3, 0.3]]))[0]]
    lo, hi, rho = tree.leaves()
    np.testing.assert_allclose((rho.astype(np.float64) * np.prod(hi - lo, axis=1)).sum(), masses.sum(), rtol=1e-6)
    htg = _write_htg(coarsen(clumpy(8).astype(np.float32), (1, 1, 1)), tmp_path / "cloud.htg")
    with pytest.raises(SceneError) as e:
        Pipeline().density(_adaptive_scene(htg, **{"dust.octree": "true"}))
    assert e.value.parameter == "dust.octree" and "cloud.htg" in str(e.value)


def test_render_writes_the_light_per_leaf_as_a_hyper_tree_grid(tmp_path):
    """`nebula-rt render --tree OUT.htg` on an adaptive scene: the .htg read back holds, per
    leaf, the J the run found (float32) and the density; for a scene on a uniform grid --tree
    is refused by name before anything is traced or written."""
    import subprocess
    import sys

    from conftest import TEST_DEVICE
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridReader

    tree = coarsen(clumpy(16).astype(np.float32), (2, 2, 2))
    _write_htg(tree, tmp_path / "cloud.htg")
    scene = tmp_path / "scene.toml"
    scene.write_text('[grid]\nshape = [16, 16, 16]\n[dust]\nmodel = "file"\nfile = "cloud.htg"\ntau = 4.0\n'
                     'floor = 0.0\n[[stars]]\nbump_radius = 0.0\n[transport]\nphotons = 20000\n'
                     f'device = "{TEST_DEVICE}"\n')
    run = [sys.executable, "-m", "nebula_rt.cli", "render", str(scene), "-o", str(tmp_path / "out.vti"), "-q"]
    r = subprocess.run(run + ["--tree", str(tmp_path / "light.htg")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    reader = vtkXMLHyperTreeGridReader()
    reader.SetFileName(str(tmp_path / "light.htg"))
    reader.Update()
    back_j = octree_from_htg(reader.GetOutput(), "J_G")
    back_rho = octree_from_htg(reader.GetOutput(), "density")
    assert back_j.n_leaves == tree.n_leaves
    lo, hi, j = back_j.leaves()
    # the same field as the run's J per leaf: its voxel averages are the .vti's J_G
    from nebula_rt.filters.vti import read_vti

    arrays, *_ = read_vti(tmp_path / "out.vti")
    np.testing.assert_allclose(box_averages(lo, hi, j, (16, 16, 16)), arrays["J_G"], rtol=1e-5, atol=1e-30)
    np.testing.assert_allclose(box_averages(*back_rho.leaves(), (16, 16, 16)), arrays["density"], rtol=1e-6)
    np.save(tmp_path / "cloud.npy", clumpy(16).astype(np.float32))
    scene.write_text(scene.read_text().replace("cloud.htg", "cloud.npy"))
    r = subprocess.run(run + ["--tree", str(tmp_path / "grid.htg")], capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "--tree" in r.stderr and "adaptive" in r.stderr, r.stderr
    assert not (tmp_path / "grid.htg").exists()


def test_the_thesis_octree_example_renders_with_its_tree(tmp_path):
    """examples/scenes/thesis-octree.toml (the procedural turbulence on an octree) through
    `nebula-rt render --tree`, smaller: the .htg holds the tree the density stage makes
    (leaf for leaf, the density's bits) and the .vti the overlap averages of its J."""
    import subprocess
    import sys

    from conftest import TEST_DEVICE
    from vtkmodules.vtkIOXML import vtkXMLHyperTreeGridReader

    from nebula_rt.backends import get_backend
    from nebula_rt.density.generate import scene_density
    from nebula_rt.filters.vti import read_vti
    from nebula_rt.scene import Scene

    example = Path(__file__).resolve().parents[2] / "examples/scenes/thesis-octree.toml"
    sets = ["grid.shape=[16,16,16]", "dust.tree_depth=5", "transport.photons=20000", f'transport.device="{TEST_DEVICE}"']
    run = [sys.executable, "-m", "nebula_rt.cli", "render", str(example), "-o", str(tmp_path / "out.vti"), "-q",
           "--tree", str(tmp_path / "light.htg")]
    for s in sets:
        run += ["--set", s]
    r = subprocess.run(run, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    tree = scene_density(Scene.load(example).with_overrides(sets), get_backend("opencl", TEST_DEVICE))
    reader = vtkXMLHyperTreeGridReader()
    reader.SetFileName(str(tmp_path / "light.htg"))
    reader.Update()
    back = octree_from_htg(reader.GetOutput(), "density")

    def by_box(t):  # the leaves in one order (an .htg numbers them depth first)
        lo_, hi_, d_ = t.leaves()
        order = np.lexsort((hi_[:, 0] - lo_[:, 0], lo_[:, 0], lo_[:, 1], lo_[:, 2]))
        return lo_[order], hi_[order], np.asarray(d_)[order]

    for a, b in zip(by_box(back), by_box(tree)):
        np.testing.assert_array_equal(a, b)
    lo, hi, j = octree_from_htg(reader.GetOutput(), "J_G").leaves()
    arrays, *_ = read_vti(tmp_path / "out.vti")
    np.testing.assert_allclose(box_averages(lo, hi, j, (16, 16, 16)), arrays["J_G"], rtol=1e-5, atol=1e-30)


def test_a_vtkhdf_hyper_tree_grid_is_read_as_its_htg(tmp_path):
    """dust.file a VTKHDF file (.vtkhdf) holding a hyper tree grid, written by VTK's own
    vtkHDFWriter: the scene traces the same tree as from the .htg of it (the same leaves and
    densities, the same packets' fates); a VTKHDF file of another data type is refused by name."""
    pytest.importorskip("vtkmodules.vtkIOHDF", reason="a VTK without VTKHDF (ParaView 5.11's reads AMR only)")
    from vtkmodules.vtkIOHDF import vtkHDFWriter

    from nebula_rt.errors import SceneError
    from nebula_rt.filters.vti import to_image_data
    from nebula_rt.pipeline import Pipeline

    tree = coarsen(clumpy(16).astype(np.float32), (2, 2, 2))
    htg = _write_htg(tree, tmp_path / "cloud.htg")
    writer = vtkHDFWriter()
    writer.SetInputData(octree_to_htg(tree, {"density": tree.density}))
    writer.SetFileName(str(tmp_path / "cloud.vtkhdf"))
    assert writer.Write() == 1
    a, b = Pipeline(), Pipeline()
    la = a.run(_adaptive_scene(htg))
    lb = b.run(_adaptive_scene(tmp_path / "cloud.vtkhdf"))
    ta, tb = a.density(_adaptive_scene(htg)), b.density(_adaptive_scene(tmp_path / "cloud.vtkhdf"))
    for x, y in zip(ta.leaves(), tb.leaves()):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(la.transport.counts, lb.transport.counts)
    image = vtkHDFWriter()
    image.SetInputData(to_image_data({"density": np.ones((4, 4, 4), np.float32)}, {}, (0.25,) * 3, (0.0,) * 3))
    image.SetFileName(str(tmp_path / "image.vtkhdf"))
    assert image.Write() == 1
    with pytest.raises(SceneError) as e:
        Pipeline().run(_adaptive_scene(tmp_path / "image.vtkhdf"))
    assert e.value.parameter == "dust.file" and "vtkImageData" in str(e.value), str(e.value)
