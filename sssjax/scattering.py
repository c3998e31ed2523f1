"""Scattering primitives shared by every transport and profile: the Fresnel terms of a
smooth dielectric boundary and their angular moments, refraction, and the
Henyey-Greenstein phase function.

Pure, `jit`/`vmap`/`grad`-compatible functions of arrays (NaN-safe through
`sssjax._numerics`). `eta` is always the index on the far side over the index on the
incident side (`n_t / n_i`); directions are unit vectors, the RGB axis (if any) last.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._numerics import safe_div, safe_sqrt

__all__ = [
    "fresnel_reflectance",
    "fresnel_transmittance",
    "fresnel_moment",
    "fresnel_moments",
    "refract",
    "hg_phase",
]

# Gauss-Legendre on [0, 1] for the Fresnel moments (smooth integrand after the substitution)
_GL_X, _GL_W = np.polynomial.legendre.leggauss(48)
_GL_X, _GL_W = 0.5 * (_GL_X + 1.0), 0.5 * _GL_W


def fresnel_reflectance(cos_i: ArrayLike, eta: ArrayLike) -> Array:
    """Exact unpolarised Fresnel reflectance of a smooth dielectric boundary.

    **Arguments:**

    - `cos_i`: cosine of the angle of incidence, measured on the side the light comes from
      (its sign is ignored).
    - `eta`: index on the far side divided by index on the incident side (`n_t / n_i`); light
      entering a medium of index 1.3 from air has `eta = 1.3`, light leaving it `1/1.3`.

    **Returns:** reflectance in [0, 1]; exactly 1 under total internal reflection.
    """
    cos_i = jnp.clip(jnp.abs(jnp.asarray(cos_i)), 0.0, 1.0)
    eta = jnp.asarray(eta)
    sin2_t = safe_div(1.0 - cos_i**2, eta**2)
    tir = sin2_t >= 1.0
    cos_t = safe_sqrt(1.0 - sin2_t)
    rs = safe_div(cos_i - eta * cos_t, cos_i + eta * cos_t, 1.0)
    rp = safe_div(eta * cos_i - cos_t, eta * cos_i + cos_t, 1.0)
    return jnp.where(tir, 1.0, 0.5 * (rs**2 + rp**2))


def fresnel_transmittance(cos_i: ArrayLike, eta: ArrayLike) -> Array:
    """`1 - fresnel_reflectance(cos_i, eta)`: the transmitted fraction of energy."""
    return 1.0 - fresnel_reflectance(cos_i, eta)


def fresnel_moment(eta: ArrayLike, k: int) -> Array:
    """`C_k(eta) = int_0^1 F_r(mu) mu^k dmu`: moment of the exact Fresnel reflectance of light
    inside a medium of relative index `eta` (inside / outside) meeting its boundary at
    `cos = mu` (pbrt's `FresnelMoment1/2` are polynomial fits of `C_1`, `C_2`).

    Below the critical cosine `mu_c = sqrt(1 - 1/eta^2)` (`eta > 1`) the reflectance is 1 and
    that part is exact; above it the substitution `mu = mu_c + (1 - mu_c) t^2` removes the
    square-root kink at the critical angle, and a 48-point Gauss-Legendre rule is exact to
    float precision. `2 C_1` is the diffuse Fresnel reflectance `F_dr`.

    **Arguments:** `eta` (> 0, any shape); `k` the moment order (0, 1, 2, ...).

    **Returns:** `C_k`, dimensionless, shape of `eta`.
    """
    return fresnel_moments(eta, (k,))[0]


def fresnel_moments(eta: ArrayLike, ks: tuple[int, ...]) -> tuple[Array, ...]:
    """`fresnel_moment(eta, k)` for each `k` in `ks`, sharing one Fresnel evaluation."""
    eta = jnp.asarray(eta)
    dt = jnp.result_type(eta, float)
    eta = eta.astype(dt)
    x, w = jnp.asarray(_GL_X, dt), jnp.asarray(_GL_W, dt)
    mu_c = safe_sqrt(1.0 - safe_div(1.0, eta**2, 1.0))[..., None]
    mu = mu_c + (1.0 - mu_c) * x**2
    fr = fresnel_reflectance(mu, 1.0 / eta[..., None]) * w * 2.0 * (1.0 - mu_c) * x
    return tuple(mu_c[..., 0] ** (k + 1) / (k + 1) + jnp.sum(fr * mu**k, axis=-1) for k in ks)


def refract(d: Array, n: Array, eta: Array) -> tuple[Array, Array]:
    """Refract unit direction `d` at a boundary with unit normal `n` (`d . n < 0`).

    **Arguments:** `d`, `n` `(..., 3)`; `eta = n_t / n_i` broadcasting against `(..., 1)`.

    **Returns:** `(t, ok)`, the refracted unit direction `(..., 3)` and whether it exists
    `(...)` (False under total internal reflection).
    """
    cos_i = -jnp.sum(d * n, axis=-1, keepdims=True)
    inv = 1.0 / eta
    sin2_t = inv**2 * (1.0 - cos_i**2)
    ok = sin2_t < 1.0
    cos_t = jnp.sqrt(jnp.where(ok, 1.0 - sin2_t, 1.0))
    t = inv * d + (inv * cos_i - cos_t) * n
    t = t / jnp.linalg.norm(t, axis=-1, keepdims=True)
    return t, ok[..., 0]


def hg_phase(cos_theta: ArrayLike, g: ArrayLike) -> Array:
    """Henyey-Greenstein phase function `(1 - g^2) / (4 pi (1 + g^2 - 2 g cos)^{3/2})`.

    **Arguments:** `cos_theta`, cosine between the propagation directions before and after
    scattering (forward scattering is `cos_theta = 1`); `g` with `|g| < 1`.

    **Returns:** the phase function in sr^-1 (integrates to 1 over the sphere).
    """
    g = jnp.asarray(g)
    denom = 1.0 + g**2 - 2.0 * g * jnp.asarray(cos_theta)
    return (1.0 - g**2) / (4.0 * jnp.pi * denom * safe_sqrt(denom))
