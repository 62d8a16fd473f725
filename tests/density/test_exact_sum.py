"""The density's exact sum (nebula_rt.exact_sum and kernels/density.cl's significand_sums):
against the exact rational sum of the values (Python's fractions, an oracle that shares no
code with either), on the host and on the device, which must agree bin for bin."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
from nebula_rt import exact_sum
from nebula_rt.scene import Scene

TINY = np.finfo(np.float32).tiny
SPECIALS = np.array([0.0, -0.0, 1e-45, -1e-45, TINY, TINY / 2, 1.0, -1.0, 3.4028235e38, -3.4028235e38,
                     2.0**-126, 2.0**-127, 1.5, 0.1], np.float32)


def oracle_sum(a) -> Fraction:
    return sum((Fraction(float(x)) for x in np.ravel(a)), Fraction(0))


def arrays():
    rng = np.random.default_rng(11)
    wide = (rng.lognormal(0.0, 8.0, 5003) * rng.choice([-1.0, 1.0], 5003)).astype(np.float32)
    # runs of one exponent broken at every length, as a smooth density's neighbours are
    steps = np.repeat(np.array([1.0, 3.0, 0.75, 1e-40, 1e30], np.float32), [1, 63, 64, 65, 130])
    return {"specials": SPECIALS, "wide": wide, "runs": steps, "one": np.array([2.5], np.float32),
            "uniform": np.full(4099, 0.37, np.float32), "empty": np.zeros(0, np.float32)}


@pytest.mark.parametrize("name", list(arrays()))
def test_host_bins_add_to_the_exact_sum(name):
    a = arrays()[name]
    bins = exact_sum.significand_sums(a)
    assert Fraction(exact_sum.exact_total(bins), 2**150) == oracle_sum(a)
    want = float(oracle_sum(a) / a.size) if a.size else 0.0  # Fraction -> float rounds once
    assert exact_sum.exact_mean(bins, a.size) == want


@pytest.mark.parametrize("name", [n for n in arrays() if n != "empty"])
def test_device_bins_are_the_hosts(backend, name):
    a = arrays()[name]
    dev = backend.to_device(a)
    assert [int(b) for b in backend.significand_sums(dev, a.size)] == exact_sum.significand_sums(a)


def test_the_mean_ignores_layout_and_order():
    """The same values in any memory layout, order or slicing have the same sum: exactness,
    not one summation order, makes the device's and the host's agree."""
    rng = np.random.default_rng(5)
    a = rng.lognormal(0.0, 2.0, (17, 23, 29)).astype(np.float32)
    m = exact_sum.mean_float32(a)
    assert exact_sum.mean_float32(np.asfortranarray(a)) == m
    assert exact_sum.mean_float32(a.transpose(2, 0, 1)) == m
    assert exact_sum.mean_float32(rng.permutation(a.ravel())) == m
    sub = a[:, ::3, 1:]  # not one block of memory
    assert exact_sum.mean_float32(sub) == float(oracle_sum(sub) / sub.size)


def test_significand_sums_take_float32_only():
    with pytest.raises(TypeError, match="float32"):
        exact_sum.significand_sums(np.ones(3))


def test_a_generated_density_has_its_mean_from_the_device_once(backend, monkeypatch):
    """The backend's mean of the density it made is the host's exact mean of the same array,
    reduced on the device once however often it is asked for."""
    from nebula_rt.density import generate_density

    scene = Scene.from_dict({"grid": {"shape": [24, 20, 18]}, "dust": {"model": "turbulence"},
                             "stars": [{"position": [0.5, 0.5, 0.5], "bump_radius": 0.05}]})
    rho = generate_density(scene, backend)
    calls = []
    real = type(backend).significand_sums
    monkeypatch.setattr(type(backend), "significand_sums", lambda self, *a: calls.append(1) or real(self, *a))
    if hasattr(backend, "cp"):  # CUDA reads the sums back with the extremes
        real_stats = type(backend).device_density_stats
        monkeypatch.setattr(type(backend), "device_density_stats",
                            lambda self, *a: calls.append(1) or real_stats(self, *a))
    backend._density_stats_of = None
    m = backend.density_mean(rho)
    assert m == exact_sum.mean_float32(np.asarray(rho)) == float(oracle_sum(rho) / rho.size)
    assert backend.density_mean(rho) == m
    # (the extremes come with the sums where the device reduces them: CUDA)
    assert backend.density_extremes(rho) in (None, (float(rho.min()), float(rho.max())))
    assert len(calls) == 1
    assert backend.density_mean(np.array(rho)) is None  # a copy has no device twin
