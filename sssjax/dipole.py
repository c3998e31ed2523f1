"""The BSSRDF of Jensen, Marschner, Levoy and Hanrahan (2001).

Pure, `jit`/`vmap`/`grad`/`jacfwd`-compatible functions of arrays. Every coefficient may be
an RGB triple and every distance a batch: arguments broadcast against each other with the
usual NumPy rules (put the RGB axis last). Lengths are in **mm**, coefficients in **mm^-1**.

Naming follows the paper and pbrt: `sigma_a`, `sigmap_s` (reduced scattering), `sigmap_t`,
`alpha_p` (reduced albedo), `sigma_tr` (effective transport coefficient), `z_r`, `z_v` (depths
of the real and virtual sources), `d_r`, `d_v` (distances to them), `F_dr`, `A`.

The boundary's Fresnel terms and the Henyey-Greenstein phase function live in
`sssjax.scattering` (re-exported here: `dipole.fresnel_reflectance`, ...).

All square roots and divisions that can reach zero use the double-`where` idiom, so values
and gradients stay finite at `r = 0`, `sigma_a = 0` and grazing angles.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ._numerics import safe_div, safe_sqrt
from .scattering import fresnel_reflectance, fresnel_transmittance, hg_phase

__all__ = [
    "F_dr",
    "A_boundary",
    "fresnel_reflectance",
    "fresnel_transmittance",
    "Rd",
    "Rd_total",
    "Sd",
    "hg_phase",
    "refracted_distance",
    "sigma_tc",
    "single_scatter_integrand",
    "single_scatter_kernel",
    "single_scatter_flat",
]


# --- boundary ---------------------------------------------------------------------------
def F_dr(eta: ArrayLike) -> Array:
    """Diffuse Fresnel reflectance of a dielectric boundary (polynomial fit).

    For `eta >= 1` (light inside the denser medium; the case of the dipole) this is
    `-1.440/eta^2 + 0.710/eta + 0.668 + 0.0636 eta` (Egan & Hilgeman 1973, as in Jensen 2001);
    for `eta < 1` the matching fit `-0.4399 + 0.7099/eta - 0.3319/eta^2 + 0.0636/eta^3`.

    **Arguments:** `eta`, relative index of refraction (inside / outside).

    **Returns:** `F_dr`, dimensionless.
    """
    eta = jnp.asarray(eta)
    inner = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    outer = -0.4399 + 0.7099 / eta - 0.3319 / eta**2 + 0.0636 / eta**3
    return jnp.where(eta >= 1.0, inner, outer)


def A_boundary(eta: ArrayLike) -> Array:
    """The boundary-condition constant `A = (1 + F_dr) / (1 - F_dr)`."""
    f = F_dr(eta)
    return (1.0 + f) / (1.0 - f)


# --- multiple scattering: the classic dipole -------------------------------------------
def _dipole_terms(sigma_a, sigmap_s, eta):
    sigma_a = jnp.asarray(sigma_a)
    sigmap_s = jnp.asarray(sigmap_s)
    sigmap_t = sigma_a + sigmap_s
    alpha_p = safe_div(sigmap_s, sigmap_t)
    sigma_tr = safe_sqrt(3.0 * sigma_a * sigmap_t)
    z_r = safe_div(1.0, sigmap_t, jnp.inf)
    z_v = z_r * (1.0 + 4.0 / 3.0 * A_boundary(eta))
    return alpha_p, sigma_tr, z_r, z_v


def Rd(r: ArrayLike, sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike) -> Array:
    """Diffuse reflectance profile `R_d(r)` of the classic dipole (corrected form).

    `R_d(r) = alpha_p/(4 pi) [z_r (1 + sigma_tr d_r) e^{-sigma_tr d_r}/d_r^3
                              + z_v (1 + sigma_tr d_v) e^{-sigma_tr d_v}/d_v^3]`
    with `z_r = 1/sigmap_t`, `z_v = z_r (1 + 4A/3)`, `d = sqrt(r^2 + z^2)`.

    **Arguments:**

    - `r`: distance between entry and exit points, mm (any batch shape).
    - `sigma_a`, `sigmap_s`: absorption and reduced scattering coefficients, mm^-1 (> 0 sum).
    - `eta`: relative index of refraction.

    **Returns:** `R_d(r)` in mm^-2 (radiant exitance per unit incident flux), broadcast shape.
    """
    alpha_p, sigma_tr, z_r, z_v = _dipole_terms(sigma_a, sigmap_s, eta)
    r = jnp.asarray(r)
    d_r = jnp.sqrt(r**2 + z_r**2)  # z_r > 0, so never sqrt(0)
    d_v = jnp.sqrt(r**2 + z_v**2)
    real = z_r * (1.0 + sigma_tr * d_r) * jnp.exp(-sigma_tr * d_r) / d_r**3
    virtual = z_v * (1.0 + sigma_tr * d_v) * jnp.exp(-sigma_tr * d_v) / d_v**3
    return alpha_p / (4.0 * jnp.pi) * (real + virtual)


def Rd_total(sigma_a: ArrayLike, sigmap_s: ArrayLike, eta: ArrayLike) -> Array:
    """Total diffuse reflectance of the dipole, `int_0^inf 2 pi r R_d(r) dr` in closed form.

    `R_d = (alpha_p / 2) (1 + e^{-(4/3) A sqrt(3 (1 - alpha_p))}) e^{-sqrt(3 (1 - alpha_p))}`.

    **Arguments:** `sigma_a`, `sigmap_s` in mm^-1; `eta`.

    **Returns:** the dimensionless total (tends to 1 as `sigma_a -> 0`).
    """
    sigma_a = jnp.asarray(sigma_a)
    sigmap_s = jnp.asarray(sigmap_s)
    alpha_p = safe_div(sigmap_s, sigma_a + sigmap_s)
    root = safe_sqrt(3.0 * (1.0 - alpha_p))
    A = A_boundary(eta)
    return 0.5 * alpha_p * (1.0 + jnp.exp(-4.0 / 3.0 * A * root)) * jnp.exp(-root)


def Sd(
    r: ArrayLike,
    cos_i: ArrayLike,
    cos_o: ArrayLike,
    sigma_a: ArrayLike,
    sigmap_s: ArrayLike,
    eta: ArrayLike,
) -> Array:
    """Diffusion term of the BSSRDF, `S_d = (1/pi) F_t(eta, w_i) R_d(r) F_t(eta, w_o)`.

    **Arguments:** `r` in mm; `cos_i`, `cos_o` the cosines of the incident and outgoing
    directions with the surface normal (outside); `sigma_a`, `sigmap_s` in mm^-1; `eta`.

    **Returns:** `S_d` in mm^-2 sr^-1.
    """
    Ft_i = fresnel_transmittance(cos_i, eta)
    Ft_o = fresnel_transmittance(cos_o, eta)
    return Ft_i * Rd(r, sigma_a, sigmap_s, eta) * Ft_o / jnp.pi


# --- single scattering -----------------------------------------------------------------
def refracted_distance(s_i: ArrayLike, cos_i: ArrayLike, eta: ArrayLike) -> Array:
    """Jensen's refracted-distance approximation for the light's path inside the medium.

    `s'_i = s_i |w_i . n_i| / sqrt(1 - (1/eta)^2 (1 - |w_i . n_i|^2))`, where `s_i` is the
    distance from the scatter point to the boundary along the *unrefracted* light direction.

    **Arguments:** `s_i` in mm; `cos_i = w_i . n_i` (sign ignored); `eta`.

    **Returns:** `s'_i` in mm.
    """
    c = jnp.abs(jnp.asarray(cos_i))
    root = safe_sqrt(1.0 - (1.0 - c**2) / jnp.asarray(eta) ** 2)
    return safe_div(jnp.asarray(s_i) * c, root, 0.0)


def sigma_tc(sigma_t_o: ArrayLike, sigma_t_i: ArrayLike, G: ArrayLike) -> Array:
    """Combined extinction `sigma_tc = sigma_t(x_o) + G sigma_t(x_i)`, `G = |n_i.w'_o|/|n_i.w'_i|`."""
    return jnp.asarray(sigma_t_o) + jnp.asarray(G) * jnp.asarray(sigma_t_i)


def single_scatter_integrand(
    sp_o: ArrayLike,
    sp_i: ArrayLike,
    cos_i: ArrayLike,
    cos_o: ArrayLike,
    cos_phase: ArrayLike,
    sigma_s: ArrayLike,
    sigma_t: ArrayLike,
    g: ArrayLike,
    eta: ArrayLike,
) -> Array:
    """Single-scattering radiance per unit incident radiance, per mm along the refracted view ray.

    `sigma_s F_t(w_i) F_t(w_o) p(cos_phase) e^{-sigma_t s'_i} e^{-sigma_t s'_o}`. Integrated
    over `s'_o` along the refracted outgoing ray (the renderer does this by Monte Carlo with
    pdf-weighted samples), it gives Jensen's `L_o^(1)` for one light direction.

    **Arguments:**

    - `sp_o`: `s'_o`, depth of the scatter point along the refracted outgoing ray, mm.
    - `sp_i`: `s'_i`, path length inside towards the light (see `refracted_distance`), mm.
    - `cos_i`, `cos_o`: cosines of the light and view directions with the boundary normals.
    - `cos_phase`: `w'_i . w'_o` in propagation convention (argument of `hg_phase`).
    - `sigma_s`, `sigma_t` in mm^-1; `g`; `eta`.

    **Returns:** radiance / (incident radiance x mm).
    """
    F = fresnel_transmittance(cos_i, eta) * fresnel_transmittance(cos_o, eta)
    s = jnp.asarray(sp_i) + jnp.asarray(sp_o)
    return F * single_scatter_kernel(s, cos_phase, sigma_s, sigma_t, g)


def single_scatter_kernel(
    s: ArrayLike, cos_phase: ArrayLike, sigma_s: ArrayLike, sigma_t: ArrayLike, g: ArrayLike
) -> Array:
    """The medium's part of `single_scatter_integrand`: `sigma_s p(cos_phase) e^{-sigma_t s}`.

    **Arguments:** `s = s'_i + s'_o`, the refracted path length inside, mm; `cos_phase` as in
    `single_scatter_integrand`; `sigma_s`, `sigma_t` in mm^-1; `g`.

    **Returns:** mm^-1 sr^-1. The Fresnel factors depend on `eta` and the geometry only, so
    a fit (which holds `eta`) folds them into the stored sample weights once.
    """
    att = jnp.exp(-jnp.asarray(sigma_t) * jnp.asarray(s))
    return jnp.asarray(sigma_s) * hg_phase(cos_phase, g) * att


def single_scatter_flat(
    cos_i: ArrayLike,
    cos_o: ArrayLike,
    cos_phase: ArrayLike,
    G: ArrayLike,
    sigma_s: ArrayLike,
    sigma_t: ArrayLike,
    g: ArrayLike,
    eta: ArrayLike,
) -> Array:
    """Jensen's single-scattering term for a flat, semi-infinite boundary, in closed form.

    `L_o^(1) / L_i = sigma_s F p(cos_phase) / sigma_tc`: the integral of
    `single_scatter_integrand` over `s'_o` when `s'_i = G s'_o`.

    **Returns:** radiance per unit incident radiance (dimensionless).
    """
    F = fresnel_transmittance(cos_i, eta) * fresnel_transmittance(cos_o, eta)
    tc = sigma_tc(sigma_t, sigma_t, G)
    return safe_div(jnp.asarray(sigma_s) * F * hg_phase(cos_phase, g), tc)
