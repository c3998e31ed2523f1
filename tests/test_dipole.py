"""The dipole BSSRDF against closed forms, quadrature, geometry and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_differences

from sssjax import dipole, preset, preset_names

PRESETS = preset_names()


def gauss_legendre_log(f, r_min, r_max, panels=600, order=16):
    """int_{r_min}^{r_max} f(r) dr by composite Gauss-Legendre in t = log r (float64)."""
    x, w = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(np.log(r_min), np.log(r_max), panels + 1)
    a, b = edges[:-1, None], edges[1:, None]
    t = 0.5 * (b - a) * x[None] + 0.5 * (a + b)
    wt = 0.5 * (b - a) * w[None]
    r = np.exp(t).ravel()
    return np.sum(np.asarray(f(jnp.asarray(r))) * (r * wt.ravel())[..., None].squeeze(), axis=0)


# --- closed forms and reference values ------------------------------------------------
@pytest.mark.parametrize("name", PRESETS)
@pytest.mark.parametrize("channel", [0, 1, 2])
def test_profile_integrates_to_closed_form_total(x64, name, channel):
    m = preset(name)
    sa, sps, eta = (np.float64(m.sigma_a[channel]), np.float64(m.sigmap_s[channel]), 1.3)
    sigma_tr = np.sqrt(3 * sa * (sa + sps))
    z_v = (1 + 4 / 3 * 2.6) / (sa + sps)
    r_max = z_v + 60.0 / sigma_tr  # e^{-60}: far beyond float64 relevance at 1e-4
    integral = gauss_legendre_log(
        lambda r: 2 * np.pi * r * dipole.Rd(r, sa, sps, eta), 1e-10, r_max
    )
    total = float(dipole.Rd_total(sa, sps, eta))
    assert integral == pytest.approx(total, rel=1e-4)


def test_reference_F_dr_and_A():
    assert float(dipole.F_dr(1.3)) == pytest.approx(0.4448, abs=5e-4)
    assert float(dipole.A_boundary(1.3)) == pytest.approx(2.602, abs=5e-4)


def test_F_dr_matches_hemispherical_integral_of_exact_fresnel(x64):
    # F_dr is a fit to the internal diffuse reflectance: 2 int_0^1 R(mu, 1/eta) mu dmu.
    mu, w = np.polynomial.legendre.leggauss(400)
    for eta in (1.2, 1.3, 1.5):
        # split at the critical cosine so the kink is at a panel edge
        mu_c = np.sqrt(1 - 1 / eta**2)
        total = 0.0
        for lo, hi in ((0.0, mu_c), (mu_c, 1.0)):
            m = 0.5 * (hi - lo) * mu + 0.5 * (hi + lo)
            R = np.asarray(dipole.fresnel_reflectance(m, 1 / eta))
            total += np.sum(0.5 * (hi - lo) * w * 2 * m * R)
        assert float(dipole.F_dr(eta)) == pytest.approx(total, abs=0.01)


def test_marble_total_and_diffusion_length_independent():
    # computed here from the formulas, not by the package
    sp = np.array([2.19, 2.62, 3.00])
    sa = np.array([0.0021, 0.0041, 0.0071])
    eta = 1.3
    fdr = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    A = (1 + fdr) / (1 - fdr)
    ap = sp / (sp + sa)
    root = np.sqrt(3 * (1 - ap))
    total = ap / 2 * (1 + np.exp(-4 / 3 * A * root)) * np.exp(-root)
    m = preset("marble")
    np.testing.assert_allclose(dipole.Rd_total(m.sigma_a, m.sigmap_s, m.eta), total, rtol=1e-5)
    np.testing.assert_allclose(m.diffuse_mean_free_path, 1 / np.sqrt(3 * sa * (sa + sp)), rtol=1e-5)
    # and the figures from the design notes: 8.5 mm for marble's red channel
    assert float(m.diffuse_mean_free_path[0]) == pytest.approx(8.5, abs=0.05)


def test_profile_at_zero_from_formula():
    sa, sps, eta = 0.01, 1.0, 1.3
    A = float(dipole.A_boundary(eta))
    zr = 1 / (sa + sps)
    zv = zr * (1 + 4 * A / 3)
    st = np.sqrt(3 * sa * (sa + sps))
    ap = sps / (sa + sps)
    expected = ap / (4 * np.pi) * sum((1 + st * z) * np.exp(-st * z) / z**2 for z in (zr, zv))
    assert float(dipole.Rd(0.0, sa, sps, eta)) == pytest.approx(expected, rel=1e-5)


# --- shape of the profile -------------------------------------------------------------
@pytest.mark.parametrize("name", PRESETS)
def test_profile_positive_and_strictly_decreasing(x64, name):
    m = preset(name)
    r = jnp.linspace(0.0, 30.0, 3001)[:, None]
    R = np.asarray(dipole.Rd(r, m.sigma_a, m.sigmap_s, m.eta))
    assert np.all(R > 0)
    assert np.all(np.diff(R, axis=0) < 0)


@pytest.mark.parametrize("name", ["marble", "skimmilk", "ketchup", "skin1"])
def test_log_slope_tends_to_minus_sigma_tr(x64, name):
    m = preset(name)
    for c in range(3):
        sa, sps, st = m.sigma_a[c], m.sigmap_s[c], m.sigma_tr[c]
        dlog = jax.grad(lambda r: jnp.log(dipole.Rd(r, sa, sps, m.eta)))
        errs = [abs(float(dlog(k / st)) / -float(st) - 1) for k in (20.0, 100.0, 300.0)]
        assert errs[0] > errs[1] > errs[2]
        assert errs[2] < 0.01


def test_no_absorption_total_is_one(x64):
    totals = [float(dipole.Rd_total(sa, 1.0, 1.3)) for sa in (1e-2, 1e-4, 1e-6, 1e-8)]
    assert np.all(np.diff(totals) > 0)
    assert totals[-1] == pytest.approx(1.0, abs=1e-3)
    assert float(dipole.Rd_total(0.0, 1.0, 1.3)) == pytest.approx(1.0, abs=1e-12)


# --- Fresnel --------------------------------------------------------------------------
@pytest.mark.parametrize("eta", [1.0, 1.3, 1.5, 2.4, 1 / 1.3])
def test_fresnel_normal_incidence(eta):
    assert float(dipole.fresnel_reflectance(1.0, eta)) == pytest.approx(
        ((eta - 1) / (eta + 1)) ** 2, abs=1e-6
    )


def test_fresnel_against_angle_form(x64):
    # rs = -sin(ti - tt)/sin(ti + tt), rp = tan(ti - tt)/tan(ti + tt): an independent form
    for eta in (1.3, 1.5, 1 / 1.3):
        ti = np.linspace(0.05, 1.5, 60)
        st = np.sin(ti) / eta
        ok = st < 1
        ti, tt = ti[ok], np.arcsin(st[ok])
        rs = np.sin(ti - tt) / np.sin(ti + tt)
        rp = np.tan(ti - tt) / np.tan(ti + tt)
        expected = 0.5 * (rs**2 + rp**2)
        np.testing.assert_allclose(
            dipole.fresnel_reflectance(np.cos(ti), eta), expected, rtol=1e-9, atol=1e-12
        )


def test_total_internal_reflection():
    eta = 1 / 1.3  # leaving the medium
    crit = np.arcsin(eta)
    beyond = np.cos(np.linspace(crit + 1e-3, np.pi / 2, 20))
    np.testing.assert_array_equal(dipole.fresnel_reflectance(beyond, eta), 1.0)
    np.testing.assert_array_equal(dipole.fresnel_transmittance(beyond, eta), 0.0)
    assert float(dipole.fresnel_reflectance(np.cos(crit - 1e-2), eta)) < 1.0


def test_reflectance_plus_transmittance_is_one():
    c = jnp.linspace(0.0, 1.0, 101)
    for eta in (1.3, 1 / 1.3, 2.0):
        s = dipole.fresnel_reflectance(c, eta) + dipole.fresnel_transmittance(c, eta)
        np.testing.assert_allclose(s, 1.0, atol=1e-6)
        assert np.all(np.asarray(dipole.fresnel_reflectance(c, eta)) >= 0)


def test_grazing_angle_values_and_gradients_finite():
    for eta in (1.3, 1 / 1.3):
        g = jax.grad(lambda c: dipole.fresnel_transmittance(c, eta))(0.0)
        assert np.isfinite(float(g))
        assert float(dipole.fresnel_reflectance(0.0, eta)) == pytest.approx(1.0)
    g = jax.grad(lambda c: dipole.refracted_distance(1.0, c, 1.3))(0.0)
    assert np.isfinite(float(g))
    g = jax.grad(lambda c: dipole.fresnel_reflectance(c, 1 / 1.3))(np.cos(np.arcsin(1 / 1.3)))
    assert np.isfinite(float(g))


# --- derivatives ----------------------------------------------------------------------
def _central(f, x, h):
    return central_differences(f, x, h, floor=1e-3)


@pytest.mark.parametrize("name", ["marble", "ketchup", "skin1", "cream"])
@pytest.mark.parametrize("r", [0.0, 0.3, 2.0, 10.0])
def test_profile_gradients_match_central_differences(x64, name, r):
    m = preset(name)

    def f(p):  # p = [sigma_a(3), sigmap_s(3)]
        return dipole.Rd(r, p[:3], p[3:], 1.3)

    p0 = jnp.concatenate([m.sigma_a, m.sigmap_s]).astype(jnp.float64)
    fd = _central(f, p0, 1e-6)
    for jac in (jax.jacfwd(f), jax.jacrev(f)):
        np.testing.assert_allclose(jac(p0), fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("name", ["marble", "ketchup", "skimmilk"])
def test_total_gradients_match_central_differences(x64, name):
    m = preset(name)

    def f(p):
        return dipole.Rd_total(p[:3], p[3:], 1.3)

    p0 = jnp.concatenate([m.sigma_a, m.sigmap_s]).astype(jnp.float64)
    fd = _central(f, p0, 1e-6)
    for jac in (jax.jacfwd(f), jax.jacrev(f)):
        np.testing.assert_allclose(jac(p0), fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


def test_finite_at_r_zero_and_sigma_a_zero():
    for fn in (jax.jacfwd, jax.jacrev):
        J = fn(lambda p: dipole.Rd(0.0, p[0], p[1], 1.3))(jnp.array([0.0, 1.0]))
        assert np.all(np.isfinite(J))
        J = fn(lambda p: dipole.Rd_total(p[0], p[1], 1.3))(jnp.array([0.0, 1.0]))
        assert np.all(np.isfinite(J))
    assert np.isfinite(float(jax.grad(lambda r: dipole.Rd(r, 0.0, 1.0, 1.3))(0.0)))
    assert np.isfinite(float(dipole.Rd(0.0, 0.0, 1.0, 1.3)))


def test_broadcasting_over_batches_and_rgb():
    m = preset("marble")
    r = jnp.linspace(0, 5, 7).reshape(7, 1)
    assert dipole.Rd(r, m.sigma_a, m.sigmap_s, m.eta).shape == (7, 3)
    v = jax.vmap(lambda rr: dipole.Rd(rr, m.sigma_a, m.sigmap_s, m.eta))(r[:, 0])
    np.testing.assert_allclose(v, dipole.Rd(r, m.sigma_a, m.sigmap_s, m.eta), rtol=1e-6)
    jitted = jax.jit(dipole.Sd)(r, 0.5, 0.7, m.sigma_a, m.sigmap_s, m.eta)
    assert jitted.shape == (7, 3)


def test_Sd_composition():
    m = preset("skin1")
    ci, co, r = 0.3, 0.9, 1.5
    expected = (
        dipole.fresnel_transmittance(ci, 1.3)
        * dipole.Rd(r, m.sigma_a, m.sigmap_s, 1.3)
        * dipole.fresnel_transmittance(co, 1.3)
        / np.pi
    )
    np.testing.assert_allclose(
        dipole.Sd(r, ci, co, m.sigma_a, m.sigmap_s, 1.3), expected, rtol=1e-6
    )
    # reciprocity: swapping the directions leaves S_d unchanged
    np.testing.assert_allclose(
        dipole.Sd(r, ci, co, m.sigma_a, m.sigmap_s, 1.3),
        dipole.Sd(r, co, ci, m.sigma_a, m.sigmap_s, 1.3),
        rtol=1e-6,
    )


# --- single scattering ----------------------------------------------------------------
@pytest.mark.parametrize("g", [-0.7, 0.0, 0.3, 0.9])
def test_hg_normalised_with_mean_cosine_g(x64, g):
    mu, w = np.polynomial.legendre.leggauss(2000)
    p = np.asarray(dipole.hg_phase(mu, g))
    assert np.sum(2 * np.pi * w * p) == pytest.approx(1.0, rel=1e-6)
    assert np.sum(2 * np.pi * w * p * mu) == pytest.approx(g, abs=1e-6)


def test_refracted_distance_matches_snell_geometry(x64):
    # a scatter point at depth d below a flat boundary: the straight (unrefracted) distance to
    # the boundary along w_i is d / cos(ti); the refracted path is d / cos(tt), sin tt = sin ti/eta
    d, eta = 0.7, 1.3
    for ti in np.linspace(0.0, 1.5, 7):
        tt = np.arcsin(np.sin(ti) / eta)
        s_i = d / np.cos(ti)
        assert float(dipole.refracted_distance(s_i, np.cos(ti), eta)) == pytest.approx(
            d / np.cos(tt), rel=1e-10
        )


def test_single_scatter_flat_is_integral_of_integrand(x64):
    # on a flat boundary s'_i = G s'_o, so int_0^inf integrand ds'_o = sigma_s F p / sigma_tc
    m = preset("skin1").scaled(1.0)
    ci, co, cphase, G = 0.6, 0.8, -0.3, 1.7
    s, w = np.polynomial.legendre.leggauss(200)
    upper = 60.0 / float(jnp.min(m.sigma_t))
    s = 0.5 * upper * (s + 1)
    w = 0.5 * upper * w
    vals = dipole.single_scatter_integrand(
        s[:, None], G * s[:, None], ci, co, cphase, m.sigma_s, m.sigma_t, 0.2, 1.3
    )
    integral = np.sum(w[:, None] * np.asarray(vals), axis=0)
    closed = dipole.single_scatter_flat(ci, co, cphase, G, m.sigma_s, m.sigma_t, 0.2, 1.3)
    np.testing.assert_allclose(integral, closed, rtol=1e-8)
    np.testing.assert_allclose(dipole.sigma_tc(m.sigma_t, m.sigma_t, G), m.sigma_t * (1 + G))
