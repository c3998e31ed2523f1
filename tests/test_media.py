"""Medium: presets exactly as published, derived quantities, validation of user input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sssjax
from sssjax import Medium, preset

# Jensen et al. 2001, Figure 5, typed in again here (not imported from the package) so that a
# typo in the package's table is caught: name -> (sigmap_s RGB, sigma_a RGB).
PUBLISHED = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046)),
    "chicken1": ((0.15, 0.21, 0.38), (0.015, 0.077, 0.19)),
    "chicken2": ((0.19, 0.25, 0.32), (0.018, 0.088, 0.20)),
    "cream": ((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163)),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45)),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071)),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12)),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142)),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48)),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145)),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014)),
}


@pytest.mark.parametrize("name", sorted(PUBLISHED))
def test_preset_values(name):
    m = preset(name)
    sp, sa = PUBLISHED[name]
    np.testing.assert_allclose(m.sigmap_s, sp, rtol=1e-6)
    np.testing.assert_allclose(m.sigma_a, sa, rtol=1e-6)
    assert float(m.g) == 0.0 and float(m.eta) == pytest.approx(1.3)


def test_preset_names_complete_and_case_insensitive():
    assert sssjax.preset_names() == sorted(PUBLISHED)
    np.testing.assert_array_equal(preset("MaRbLe").sigma_a, preset("marble").sigma_a)


def test_unknown_preset_lists_known():
    with pytest.raises(ValueError) as e:
        preset("marbel")
    msg = str(e.value)
    assert "marbel" in msg and "did you mean 'marble'" in msg
    for name in PUBLISHED:
        assert name in msg


def test_derived_quantities_from_definitions():
    sa, ss, g = np.array([0.1, 0.2, 0.3]), np.array([2.0, 3.0, 4.0]), 0.4
    m = Medium(sa, ss, g=g, eta=1.4)
    sps = ss * (1 - g)
    spt = sa + sps
    np.testing.assert_allclose(m.sigmap_s, sps, rtol=1e-6)
    np.testing.assert_allclose(m.sigmap_t, spt, rtol=1e-6)
    np.testing.assert_allclose(m.sigma_t, sa + ss, rtol=1e-6)
    np.testing.assert_allclose(m.alpha_p, sps / spt, rtol=1e-6)
    np.testing.assert_allclose(m.albedo, ss / (sa + ss), rtol=1e-6)
    np.testing.assert_allclose(m.sigma_tr, np.sqrt(3 * sa * spt), rtol=1e-6)
    np.testing.assert_allclose(m.mean_free_path, 1 / (sa + ss), rtol=1e-6)
    np.testing.assert_allclose(m.reduced_mean_free_path, 1 / spt, rtol=1e-6)
    np.testing.assert_allclose(m.diffuse_mean_free_path, 1 / np.sqrt(3 * sa * spt), rtol=1e-6)


def test_from_reduced_roundtrip():
    m = Medium.from_reduced([0.01, 0.02, 0.03], [1.0, 2.0, 3.0], g=0.8)
    np.testing.assert_allclose(m.sigma_s, [5.0, 10.0, 15.0], rtol=1e-6)
    np.testing.assert_allclose(m.sigmap_s, [1.0, 2.0, 3.0], rtol=1e-6)


def test_scalar_broadcasts_to_rgb():
    m = Medium(0.1, 1.0)
    assert m.sigma_a.shape == (3,) and m.sigma_s.shape == (3,)


def test_sigma_a_zero_is_finite():
    m = Medium(0.0, 1.0)
    for v in (m.sigma_tr, m.alpha_p, m.diffuse_mean_free_path):
        assert not np.any(np.isnan(np.asarray(v)))
    grad = jax.grad(lambda a: Medium(a, 1.0).sigma_tr.sum())(jnp.zeros(3))
    assert np.all(np.isfinite(grad))


def test_medium_is_a_pytree_usable_in_jit_and_vmap():
    @jax.jit
    def f(m):
        return m.sigma_tr

    m = preset("marble")
    np.testing.assert_allclose(f(m), m.sigma_tr, rtol=1e-6)
    batch = jax.vmap(lambda s: Medium(m.sigma_a * s, m.sigma_s, m.g, m.eta).sigma_tr)(
        jnp.array([1.0, 4.0])
    )
    expected = Medium(m.sigma_a * 4.0, m.sigma_s, m.g, m.eta).sigma_tr
    np.testing.assert_allclose(batch[1], expected, rtol=1e-5)
    np.testing.assert_allclose(batch[0], m.sigma_tr, rtol=1e-6)


BAD = [
    (dict(sigma_a=[-0.1, 0.1, 0.1], sigma_s=1.0), "sigma_a", "-0.1"),
    (dict(sigma_a=0.1, sigma_s=[1.0, -2.0, 1.0]), "sigma_s", "-2"),
    (dict(sigma_a=[0.1, np.nan, 0.1], sigma_s=1.0), "sigma_a", "nan"),
    (dict(sigma_a=0.1, sigma_s=np.inf), "sigma_s", "inf"),
    (dict(sigma_a=0.1, sigma_s=1.0, eta=0.0), "eta", "0"),
    (dict(sigma_a=0.1, sigma_s=1.0, eta=-1.3), "eta", "-1.3"),
    (dict(sigma_a=0.1, sigma_s=1.0, g=1.0), "g", "1"),
    (dict(sigma_a=0.1, sigma_s=1.0, g=-1.5), "g", "-1.5"),
    (dict(sigma_a=[0.1, 0.2], sigma_s=1.0), "sigma_a", "shape"),
    (dict(sigma_a=0.1, sigma_s=np.ones((2, 3))), "sigma_s", "shape"),
    (dict(sigma_a=0.1, sigma_s=1.0, eta=[1.3, 1.3]), "eta", "shape"),
]


@pytest.mark.parametrize("kwargs,field,value", BAD)
def test_validation(kwargs, field, value):
    with pytest.raises(ValueError) as e:
        Medium(**kwargs)
    msg = str(e.value)
    assert f"Medium.{field}" in msg and value in msg


def test_no_checks_on_traced_values():
    # Inside jit a negative traced value must not raise (no Python checks on tracers).
    out = jax.jit(lambda a: Medium(a, 1.0).sigma_t)(jnp.array([-0.1, 0.1, 0.1]))
    assert out.shape == (3,)
