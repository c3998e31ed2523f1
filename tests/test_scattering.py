"""Scattering primitives (`sssjax.scattering`): refraction against Snell's law and the
plane of incidence; the re-exports under their old homes are the same functions."""

import jax.numpy as jnp
import numpy as np

from sssjax import dipole, profiles, scattering


def test_refract_obeys_snell_and_stays_in_the_plane_of_incidence():
    n = jnp.array([0.0, 0.0, 1.0])
    theta = np.radians([0.0, 10.0, 35.0, 60.0, 85.0])
    phi = np.radians([0.0, 40.0, 100.0, 200.0, 300.0])
    d = np.stack(
        [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], axis=-1
    )
    for eta in (1.3, 1.0, 1 / 1.3):
        t, ok = scattering.refract(jnp.asarray(d), n, jnp.full((5, 1), eta))
        t, ok = np.asarray(t), np.asarray(ok)
        sin_t = np.sin(theta) / eta
        np.testing.assert_array_equal(ok, sin_t < 1)  # total internal reflection beyond
        np.testing.assert_allclose(np.linalg.norm(t[ok], axis=-1), 1.0, rtol=1e-6)
        np.testing.assert_allclose(np.hypot(t[ok, 0], t[ok, 1]), sin_t[ok], atol=1e-6)
        assert np.all(t[ok, 2] < 0)  # onward, through the boundary
        # coplanar with the incident ray and the normal: the same azimuth
        moving = ok & (theta > 0)
        np.testing.assert_allclose(
            np.arctan2(t[moving, 1], t[moving, 0]),
            np.arctan2(d[moving, 1], d[moving, 0]),
            atol=1e-5,
        )


def test_primitives_have_one_home():
    assert dipole.fresnel_reflectance is scattering.fresnel_reflectance
    assert dipole.fresnel_transmittance is scattering.fresnel_transmittance
    assert dipole.hg_phase is scattering.hg_phase
    assert profiles.fresnel_moment is scattering.fresnel_moment
