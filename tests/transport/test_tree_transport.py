"""Transport on an octree (kernels/tree.cl, nebula_rt.transport.tree) against answers the tree
code did not make:

- a tree whose leaves are a grid's voxels: the packets draw their random numbers as the
  uniform grid's analog packets, so the counts are the grid transport's exactly and J per leaf
  its J per voxel to float32 rounding (the two walks form their faces differently);
- a uniform density on a randomly refined tree: a packet's path does not depend on how the
  medium is cut, so the counts are the uniform grid's and the total track length (sum of J x
  volume) is the grid's, to rounding;
- a pure absorber around a central star: the escaped fraction is the direction average of
  exp(-kappa s), s the distance to the cube's face (quadrature), within 5 binomial sigma.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import centre_star, one_band
from test_octree import _random_boxes  # (a random forest of octrees, tests/density)

from nebula_rt.density.octree import coarsen, from_boxes
from nebula_rt.transport import trace


def trace_tree(tree, bands, stars, **kw):
    """A run on a tree: the grid's trace with the octree for the density (analog packets)."""
    return trace(tree, bands, stars, method="analog", **kw)


def _voxel_of_leaves(tree, n):
    lo, _, _ = tree.leaves()
    return np.floor(lo * n + 1e-9).astype(int)


def test_a_tree_of_voxels_is_the_grid(backend):
    rho = (np.random.default_rng(3).random((8, 8, 8)) + 0.2).astype(np.float32)
    tree = coarsen(rho, (1, 1, 1))  # every value differs: nothing merges
    assert tree.n_leaves == 512
    kw = dict(tau=3.0, photons=20_000, seed=4)
    tl = trace_tree(tree, one_band(0.6, 0.5), centre_star(), backend=backend, **kw)
    grid = trace(rho, one_band(0.6, 0.5), centre_star(), backend=backend, method="analog", batch_size=20_000, **kw)
    np.testing.assert_array_equal(tl.counts, grid.counts)
    i = _voxel_of_leaves(tree, 8)
    np.testing.assert_allclose(tl.J[0], grid.J[0][i[:, 0], i[:, 1], i[:, 2]], rtol=1e-5)


def test_a_uniform_density_on_a_random_tree_is_the_uniform_grid(backend):
    lo, hi = _random_boxes(21)  # 3^3 roots, leaves down to 3 levels below
    tree = from_boxes(lo, hi, np.ones(len(lo)), (3, 3, 3))
    assert tree.depth() >= 2
    kw = dict(tau=4.0, photons=20_000, seed=9)
    tl = trace_tree(tree, one_band(0.7, 0.3), centre_star(), backend=backend, **kw)
    rho = np.ones((24, 24, 24), np.float32)
    grid = trace(rho, one_band(0.7, 0.3), centre_star(), backend=backend, method="analog", batch_size=20_000, **kw)
    # a packet may part from its grid twin where float32 rounding of a face crossing moves an
    # interaction point across nothing physical: the counts agree to a few packets
    assert tl.counts[0, 0] == grid.counts[0, 0] == 20_000
    assert np.abs(tl.counts[0, 1:] - grid.counts[0, 1:]).max() <= 5, (tl.counts, grid.counts)
    track_tree = (tl.J[0] * np.prod(hi - lo, axis=1)).sum()
    track_grid = grid.J[0].sum() / 24 ** 3
    assert abs(track_tree / track_grid - 1.0) < 1e-3


def test_a_pure_absorber_lets_out_the_exact_fraction(backend):
    kappa = 6.0  # per box unit: optical depth 3 to the faces' centres
    lo, hi = _random_boxes(5)
    tree = from_boxes(lo, hi, np.ones(len(lo)), (3, 3, 3))
    n = 40_000
    tl = trace_tree(tree, one_band(0.0, 0.0), centre_star(), tau=kappa, photons=n, seed=2, backend=backend)
    assert tl.counts[0, 0] == n and tl.counts[0, 1] + tl.counts[0, 2] == n
    # the direction average of exp(-kappa s), s = 0.5 / max|d_a| (Gauss-Legendre in mu, phi by symmetry)
    mu, wmu = np.polynomial.legendre.leggauss(400)
    phi = (np.arange(800) + 0.5) / 800 * 2 * math.pi
    M, P = np.meshgrid(mu, phi, indexing="ij")
    st = np.sqrt(1 - M ** 2)
    d = np.stack([st * np.cos(P), st * np.sin(P), M])
    s = 0.5 / np.abs(d).max(axis=0)
    exact = float((np.exp(-kappa * s) * wmu[:, None]).sum() / 800 / 2)
    got = tl.counts[0, 2] / n
    sigma = math.sqrt(exact * (1 - exact) / n)
    assert abs(got - exact) < 5 * sigma, (got, exact, sigma)
    assert 0.01 < exact < 0.2  # a test with teeth: neither all nor nothing gets out


def test_bad_arguments_are_refused(backend):
    tree = coarsen(np.ones((2, 2, 2)), (1, 1, 1))
    with pytest.raises(ValueError, match="photons"):
        trace_tree(tree, one_band(), centre_star(), tau=1.0, photons=0, backend=backend)


def test_a_sphere_on_a_tree_refined_at_its_surface_lets_out_p0_and_p0_plus_p1(backend):
    """A uniform sphere (tau_R = 1, albedo 0.6, g 0.6) as a tree: the partial-volume sphere on
    96^3 voxels, merged wherever the voxels agree (inside and outside), so that only its
    surface stays refined. max_scatterings 0: the escaped fraction is P0, 1: P0 + P1
    (REFERENCES.md's values, as tests/transport/test_transport_physics.py), within 5 binomial
    sigma plus the partial-volume surface's own error, measured by an independent ray march
    of the 96^3 voxels (twice for P0 + P1: before and after the scattering)."""
    from test_transport_physics import P0_TAU1, P1_TAU1_G06, numpy_escape_probability, partial_volume_sphere

    rho = partial_volume_sphere((96, 96, 96), 0.5)
    tree = coarsen(rho, (3, 3, 3))
    assert tree.n_leaves < 96 ** 3 / 4 and tree.depth() == 5  # refined only where it must be
    kappa, n = 2.0, 300_000
    vox_err = abs(numpy_escape_probability(rho.astype(np.float64), kappa, n_dirs=2000) - P0_TAU1)
    assert vox_err < 2e-3
    esc = []
    for ms, seed in ((0, 3), (1, 4)):
        tl = trace_tree(tree, one_band(0.6, 0.6), centre_star(), tau=kappa, photons=n, seed=seed,
                        max_scatterings=ms, backend=backend)
        assert tl.counts[0, 1:].sum() == n
        esc.append(tl.counts[0, 2] / n)
    s0 = math.sqrt(P0_TAU1 * (1 - P0_TAU1) / n)
    p01 = P0_TAU1 + P1_TAU1_G06
    s1 = math.sqrt(p01 * (1 - p01) / n)
    assert abs(esc[0] - P0_TAU1) < 5 * s0 + vox_err + 5e-4, (esc[0], P0_TAU1)
    assert abs(esc[1] - p01) < 5 * s1 + 2 * vox_err + 5e-4, (esc[1], p01)


@pytest.mark.parametrize("direction", [(0.0, 0.0, -1.0), (0.3, -0.5, 0.8)])
def test_a_tree_of_voxels_peels_off_the_grids_image(backend, direction):
    """The peel-off image on a tree of a grid's voxels: the same scatterings and the same
    stochastic rounding draws as the grid's analog packets, the optical depths to the edge
    marched leaf by leaf instead of voxel by voxel (or read from the columns along an axis):
    the images agree to float32 rounding (totals within 1e-5), along an axis and obliquely."""
    from nebula_rt.observe.sky import Camera

    rho = (np.random.default_rng(5).random((8, 8, 8)) + 0.2).astype(np.float32)
    tree = coarsen(rho, (1, 1, 1))
    cam = Camera(direction=direction, size=(16, 12), center=(0.5, 0.5, 0.5))
    kw = dict(tau=3.0, photons=20_000, seed=7)
    tl = trace_tree(tree, one_band(0.6, 0.5), centre_star(), backend=backend, peel=cam, **kw)
    grid = trace(rho, one_band(0.6, 0.5), centre_star(), backend=backend, method="analog", batch_size=20_000,
                 peel=cam, light_field=False, **kw)
    assert tl.peel_image.sum() > 0
    np.testing.assert_allclose(tl.peel_image.sum(), grid.peel_image.sum(), rtol=1e-5)
    np.testing.assert_allclose(tl.peel_image, grid.peel_image, rtol=1e-4, atol=1e-4 * grid.peel_image.max())


def test_a_thin_sphere_on_a_tree_peels_off_its_single_scattering_image(backend):
    """The thin sphere of tests/observe/test_sky_physics.py (tau_R 0.05, albedo 0.5, g 0.6,
    at most one scattering) as a tree refined at its surface: the image in three rings of
    projected offset against the single-scattering integral with the phase function
    (test_sky_physics.single_scattering_hg), within 5 standard errors of 3 seeds' mean plus
    1.5 % for the partial-volume surface."""
    from test_sky_physics import L, N, R, single_scattering_hg
    from test_transport_physics import partial_volume_sphere

    from nebula_rt.observe.sky import Camera

    g, omega, tau_r = 0.6, 0.5, 0.05
    kappa = tau_r / R
    rho = partial_volume_sphere((N, N, N), R)
    tree = coarsen(rho, (N // 16,) * 3)
    assert tree.n_leaves < N ** 3 / 3
    cam = Camera(direction=(0.0, 0.0, -1.0), size=(64, 64), extent=1.0)
    images = [trace_tree(tree, one_band(albedo=omega, g=g), centre_star(L), tau=kappa, photons=600_000, seed=s,
                         max_scatterings=1, peel=cam, backend=backend).peel_image[0] for s in (1, 2, 3)]
    p = np.arange(64)
    P, Q = np.meshgrid(p, p, indexing="ij")
    px = cam.pixel_size
    origin = cam.origin()
    b = np.hypot(origin[0] + px * P - 0.5, origin[1] + px * Q - 0.5)
    want_px = single_scattering_hg(b, kappa, g, omega)
    for lo, hi in ((0.1, 0.175), (0.175, 0.25), (0.25, 0.35)):
        m = (b >= lo) & (b < hi)
        got = np.array([im[m].mean() for im in images])
        want = want_px[m].mean()
        se = got.std(ddof=1) / math.sqrt(len(got))
        assert abs(got.mean() / want - 1) < 5 * se / want + 0.015, (lo, got.mean() / want, se / want)
        assert se / want < 0.03


def _far_leaves(lo, hi, star, factor=1.5):
    """Leaves whose nearest point lies at least ``factor`` of their edge from the star (the
    quadrature of J's 1/r^2 is good there)."""
    nearest = np.clip(np.asarray(star)[None, :], lo, hi)
    dist = np.linalg.norm(nearest - np.asarray(star)[None, :], axis=1)
    return dist >= factor * (hi - lo).max(axis=1)


@pytest.mark.parametrize("error_estimate,method", [("batches", "analog"), ("packets", "analog"),
                                                   ("batches", "biased")])
def test_the_stated_errors_on_a_tree_are_honest(backend, error_estimate, method):
    """A pure absorber on a randomly refined tree: J per leaf against its exact average of
    L e^(-kappa r) / (16 pi^2 r^2) over the leaf (Gauss-Legendre, nebula_rt.transport.analytic),
    4 seeds. The summed squared deviations over the summed stated variances, R, is 1 for an
    honest error (the batch-means variance and the per-packet one are unbiased: no packet
    enters a leaf twice without scattering); measured 0.95-1.05. The leaves share packets, so
    R scatters more than independent leaves' would (0.03): |R - 1| < 0.2 still fails an
    error stated 10 % low (R = 1.23). Every leaf's J also lies within 7 of its stated sigma
    of the exact average (the quadrature's own error, order 6 against 8, is added): with 16
    batches the deviation over the stated sigma is t-distributed with 15 degrees of freedom,
    which passes 5 in one of about 6000 leaves (measured: at most 5.0 over 1616). Weighted
    packets (every flight forced to the box's edge, its expected track length deposited leaf
    by leaf) the same."""
    from nebula_rt.transport.analytic import box_average_point_source

    lo, hi = _random_boxes(17)
    tree = from_boxes(lo, hi, np.ones(len(lo)), (3, 3, 3))
    assert tree.depth() >= 2
    kappa, star, n = 2.0, (0.5, 0.5, 0.5), 200_000
    # leaves away from the star that at least 100 packets cross in expectation (the batch
    # means need a few per batch): n x the leaf's solid angle / 4 pi x e^(-kappa r)
    r = np.maximum(np.linalg.norm(0.5 * (lo + hi) - np.asarray(star)[None, :], axis=1), 1e-9)
    crossings = n * (hi - lo).prod(axis=1) ** (2 / 3) / (4 * math.pi * r**2) * np.exp(-kappa * r)
    far = _far_leaves(lo, hi, star) & (crossings >= 100)
    exact = box_average_point_source(lo[far], hi[far], star, kappa, 1.0, order=8)
    quad = np.abs(box_average_point_source(lo[far], hi[far], star, kappa, 1.0, order=6) - exact)
    assert far.sum() > 150 and np.all(quad < 1e-3 * exact)
    dev2 = var = 0.0
    for seed in (1, 2, 3, 4):
        res = trace(tree, one_band(0.0, 0.0), centre_star(), tau=kappa, photons=n, seed=seed,
                    backend=backend, error_estimate=error_estimate, method=method)
        assert res.J.shape == (1, tree.n_leaves) and res.error_estimate == error_estimate
        J, sigma = res.J[0][far], (res.J[0] * res.rel_error[0])[far]
        assert np.all(np.abs(J - exact) < 7 * sigma + quad), seed
        dev2 += float(np.sum((J - exact) ** 2))
        var += float(np.sum(sigma**2))
    ratio = dev2 / var
    assert abs(ratio - 1.0) < 0.2, ratio


def test_a_run_on_a_tree_reports_progress_and_cancels():
    """Batches traced in short launches: progress goes up to the packets asked for, and a
    cancel asked for after the first report ends the run with CancelledError."""
    from conftest import tuned_backend

    from nebula_rt.errors import CancelledError

    lo, hi = _random_boxes(3)
    tree = from_boxes(lo, hi, np.ones(len(lo)), (3, 3, 3))
    backend = tuned_backend({})
    backend.launch_packets = backend.first_launch_packets = 4000  # two batches a launch
    seen = []
    res = trace_tree(tree, one_band(0.6, 0.6), centre_star(), tau=2.0, photons=32_000, batch_size=2000,
                     backend=backend, progress=lambda done, total: seen.append((done, total)))
    assert res.batches == 16 and seen[-1] == (32_000, 32_000) and len(seen) >= 8
    assert [d for d, _ in seen] == sorted(d for d, _ in seen)
    asked = []
    with pytest.raises(CancelledError):
        trace_tree(tree, one_band(0.6, 0.6), centre_star(), tau=2.0, photons=32_000, batch_size=2000,
                   backend=backend, progress=lambda done, total: asked.append(done), cancel=lambda: bool(asked))


def _refined(tree, rng, rounds=2, fraction=0.4):
    """``tree`` with a random ``fraction`` of its leaves split into 8 of the same value,
    ``rounds`` times (the same medium, cut into more leaves)."""
    lo, hi, v = (np.array(a, np.float64) for a in tree.leaves())
    octants = np.array(list(np.ndindex(2, 2, 2)))[:, ::-1]
    for _ in range(rounds):
        pick = rng.random(len(v)) < fraction
        half = (hi[pick] - lo[pick]) / 2
        new_lo = (lo[pick][:, None, :] + octants[None] * half[:, None, :]).reshape(-1, 3)
        new_hi = new_lo + np.repeat(half, 8, axis=0)
        lo, hi = np.concatenate([lo[~pick], new_lo]), np.concatenate([hi[~pick], new_hi])
        v = np.concatenate([v[~pick], np.repeat(v[pick], 8)])
    return from_boxes(lo, hi, v, tree.roots)


@pytest.mark.parametrize("tau", [10.0, 30.0])
def test_weighted_packets_on_a_tree_transmit_the_exact_light_of_a_thick_slab(backend, tau):
    """The thick slab of tests/transport/test_thick_slab.py (4 layers, lit from just above, a
    peel-off camera below) as a randomly refined tree, weighted packets: the transmitted
    T(mu = 1) of 8 runs of 20,000 packets against the adding-doubling solution within 5
    standard errors of their mean (from the runs' stated errors), each run's pull within 4,
    and the mean absorbed fraction within 5 of its standard errors and 1 %. Analog packets would need about e^tau of them."""
    import warnings

    from oracles.plane_parallel import PointSourceSlab, Slab
    from slab_scene import image_power, peel_bins, slab

    from nebula_rt.errors import NebulaWarning

    rho, bands, stars, kappa, cam = slab(tau)
    tree = _refined(coarsen(rho, (1, 1, 16)), np.random.default_rng(1))
    assert tree.depth() == 2 and tree.n_leaves > 100
    oracle = PointSourceSlab(Slab(tau, 0.6, 0.6))
    exact = oracle.transmitted(1.0)
    vals, errs, absorbed = [], [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NebulaWarning)
        for seed in range(1, 9):
            res = trace(tree, bands, stars, tau=kappa, photons=20_000, seed=seed, backend=backend, method="biased",
                        peel=cam, peel_bins=peel_bins(cam), light_field=False)
            v, se = image_power(res, cam)
            vals.append(v / exact)
            errs.append(se / exact)
            absorbed.append(res.energy[0][1] / oracle.absorbed)
    vals, errs, absorbed = np.array(vals), np.array(errs), np.array(absorbed)
    se_absorbed = absorbed.std(ddof=1) / math.sqrt(absorbed.size)
    assert abs(absorbed.mean() - 1.0) < 5 * se_absorbed + 1e-4 and abs(absorbed.mean() - 1.0) < 0.01, absorbed
    se_mean = math.sqrt(np.sum(errs**2)) / vals.size
    assert abs(vals.mean() - 1.0) < 5 * se_mean and se_mean < 0.05, (vals, errs)
    assert np.all(np.abs(vals - 1.0) < 4 * errs), (vals, errs)


def test_weighted_packets_on_a_tree_give_the_same_bits_whatever_the_launches(backend):
    """Weighted packets on a random tree (track-length J and a peel-off image): their sums,
    squares, energies and image do not depend on how the batches are cut into launches."""
    from nebula_rt.observe.sky import Camera

    lo, hi = _random_boxes(8)
    tree = from_boxes(lo, hi, np.random.default_rng(2).random(len(lo)) + 0.1, (3, 3, 3))
    cam = Camera(direction=(0.2, 0.3, -0.9), size=(12, 10))
    runs = []
    for launch in (1 << 30, 3 * 1500):
        from conftest import tuned_backend

        be = tuned_backend({})
        be.launch_packets = launch
        runs.append(trace(tree, one_band(0.7, 0.4), centre_star(), tau=12.0, photons=12_000, batch_size=1500,
                          seed=5, backend=be, peel=cam, method="biased"))
    np.testing.assert_array_equal(runs[1].raw_sum, runs[0].raw_sum)
    np.testing.assert_array_equal(runs[1].raw_m2, runs[0].raw_m2)
    np.testing.assert_array_equal(runs[1].energy, runs[0].energy)
    np.testing.assert_array_equal(runs[1].peel_image, runs[0].peel_image)
    assert runs[0].method == "biased" and np.all(runs[0].J[0] >= 0) and runs[0].J[0].max() > 0


def test_a_tree_of_voxels_gives_the_same_bits_whatever_the_kernel_path(backend):
    """A tree's run through the grid's machinery: its batch sums, squares, counts and image do
    not depend on the work-group sums, on how the batches are cut into launches, or on how the
    walk finds the next leaf (from the root grid, or from the lowest shared ancestor:
    NRT_TREE_ASCEND)."""
    from conftest import tuned_backend

    from nebula_rt.observe.sky import Camera

    lo, hi = _random_boxes(8)
    tree = from_boxes(lo, hi, np.random.default_rng(2).random(len(lo)) + 0.1, (3, 3, 3))
    cam = Camera(direction=(0.2, 0.3, -0.9), size=(12, 10))
    runs = []
    for tuning, launch in (({"NRT_GROUP_TALLY": 0}, 1 << 30), ({"NRT_GROUP_TALLY": 1}, 1 << 30),
                           ({"NRT_GROUP_TALLY": 1}, 3 * 1500), ({"NRT_TREE_ASCEND": 1}, 1 << 30),
                           ({"NRT_TREE_ASCEND": 0}, 1 << 30)):
        be = tuned_backend(tuning)
        be.launch_packets = launch
        runs.append(trace_tree(tree, one_band(0.7, 0.4), centre_star(), tau=6.0, photons=12_000,
                               batch_size=1500, seed=5, backend=be, peel=cam))
    for res in runs[1:]:
        np.testing.assert_array_equal(res.counts, runs[0].counts)
        np.testing.assert_array_equal(res.raw_sum, runs[0].raw_sum)
        np.testing.assert_array_equal(res.raw_m2, runs[0].raw_m2)
        np.testing.assert_array_equal(res.peel_image, runs[0].peel_image)
    assert runs[0].peel_error is not None and np.isfinite(runs[0].peel_error).any()
