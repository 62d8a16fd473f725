"""Henyey-Greenstein sampling as the transport kernel runs it (float32).

Moments: for HG, <mu> = g and Var(mu) = (1 - g^2)/3. With n samples the sample mean has
standard error sqrt(Var/n) and the sample variance sqrt((m4 - Var^2)/n), m4 the fourth central
moment (integrated numerically from the pdf). Assertions are at 5 sigma.
"""

import numpy as np
import pytest
from scipy import integrate

from nebula_rt.backends import probes

N = 2_000_000
GS = [-0.99, -0.5, 0.0, 1e-7, 1e-4, 0.6, 0.99]


def hg_pdf(mu, g):
    return 0.5 * (1 - g * g) / (1 + g * g - 2 * g * mu) ** 1.5


def hg_inverse_cdf(xi, g):
    """Exact inverse CDF in float64 (the branch-free form, with the g -> 0 limit)."""
    xi = np.asarray(xi, np.float64)
    d = 1 - g + 2 * g * xi
    return (2 * xi * (1 + g * g) * (1 - g + g * xi) - (1 - g) ** 2) / d**2


def central_moment4(g):
    var = (1 - g * g) / 3
    pts = [g] if abs(g) > 0.5 else None
    return integrate.quad(lambda m: (m - g) ** 4 * hg_pdf(m, g), -1, 1, points=pts, limit=200)[0], var


@pytest.mark.parametrize("g", GS)
def test_hg_moments(backend, g):
    mu, norm = probes.hg_cosines(backend, g, seed=11, n=N)
    mu = mu.astype(np.float64)
    assert np.all(np.isfinite(mu)) and np.all(np.abs(mu) <= 1.0 + 1e-6)
    # the kernel clamps |g| <= 1 - 1e-4 in float32; compare with the clamped value
    gk = kernel_g(g)
    m4, var = central_moment4(gk)
    se_mean = np.sqrt(var / N)
    se_var = np.sqrt(max(m4 - var * var, 0.0) / N)
    # float32 direction rounding adds up to ~1e-6 to each cosine
    assert abs(mu.mean() - gk) < 5 * se_mean + 2e-6, (mu.mean(), gk, se_mean)
    assert abs(mu.var() - var) < 5 * se_var + 2e-6, (mu.var(), var, se_var)
    assert np.all(np.abs(norm - 1.0) < 1e-5)


def test_orientation_forward_and_backward(backend):
    """mu is measured between the NEW and OLD directions: forward scattering keeps going."""
    fwd, _ = probes.hg_cosines(backend, 0.9, seed=3, n=100_000)
    back, _ = probes.hg_cosines(backend, -0.9, seed=3, n=100_000)
    assert np.median(fwd) > 0.9 and np.median(back) < -0.9


def hg_cdf(mu, g):
    """F(mu) = (1-g^2)/(2g) [(1+g^2-2g mu)^-1/2 - (1+g)^-1], and (mu+1)/2 at g = 0."""
    mu = np.asarray(mu, np.float64)
    if g == 0:
        return (mu + 1) / 2
    return (1 - g * g) / (2 * g) * ((1 + g * g - 2 * g * mu) ** -0.5 - 1 / (1 + g))


def hg_cdf_from(mu, one_minus_abs, sign_src, g):
    """F(mu) with 1 + g^2 - 2 g mu written as (1 - g)^2 + 2 g (1 - mu) (or (1 + g)^2 - 2 g (1 + mu))
    so that mu near +-1 loses nothing."""
    if g == 0:
        return (mu + 1) / 2
    q = np.where(sign_src > 0, (1 - g) ** 2 + 2 * g * one_minus_abs, (1 + g) ** 2 - 2 * g * one_minus_abs)
    return (1 - g * g) / (2 * g) * (q**-0.5 - 1 / (1 + g))


def kernel_g(g):
    """The kernel clamps |g| <= 1 - 1e-4 in float32."""
    lim = np.float32(1) - np.float32(1e-4)
    return float(np.clip(np.float32(g), -lim, lim))


@pytest.mark.parametrize("g", GS + [-1.0, 1.0, -0.999999, 0.999999, 1e-5, -1e-7])
def test_hg_inverse_cdf_pointwise(backend, g):
    """Each sample sits at its quantile: F(mu(xi)) = xi to float32 precision, including
    xi = 0 and 1, |g| -> 1 and tiny |g| where the textbook formula cancels (g = 1e-7 gives
    mu = 0 instead of 0.4 there). The quantile is the right yardstick: where the pdf is tiny
    (g -> -1, mu -> 1) mu itself is ill-conditioned in xi."""
    xi = np.concatenate([[0.0, 1.0, 1 - 2**-24, 2**-24], np.linspace(0, 1, 1001)]).astype(np.float32)
    mu, st = probes.hg_at(backend, g, xi)
    gk = kernel_g(g)
    assert np.all(np.isfinite(mu)) and np.all(np.isfinite(st))
    # 1 - |mu| from sin(theta), which the kernel computes separately and the rotation uses: mu
    # itself rounds to +-1 in float32 when 1 - |mu| < 6e-8 (g -> 1), sin(theta) does not.
    m = mu.astype(np.float64)
    s2 = st.astype(np.float64) ** 2
    one_minus_abs = np.where(np.abs(m) > 0.5, s2 / (1 + np.abs(m)), 1 - np.abs(m))
    mu_acc = np.sign(m) * (1 - one_minus_abs)
    quantile_error = np.abs(hg_cdf_from(mu_acc, one_minus_abs, m, gk) - xi.astype(np.float64))
    assert quantile_error.max() < 2e-6, (quantile_error.max(), xi[np.argmax(quantile_error)])
    # where mu is well conditioned it is also accurate pointwise
    want = hg_inverse_cdf(xi.astype(np.float64), gk)
    well = 0.5 * (1 - gk * gk) / (1 + gk * gk - 2 * gk * want) ** 1.5 > 0.05
    assert np.max(np.abs(mu - want)[well]) < 5e-6
    assert abs(mu[0] + 1) < 1e-6 and abs(mu[1] - 1) < 1e-6
    # sin(theta) consistent with mu and in [0, 1]
    assert np.all(st >= 0) and np.all(st <= 1)
    assert np.max(np.abs(st.astype(np.float64) ** 2 + want**2 - 1)) < 1e-4
