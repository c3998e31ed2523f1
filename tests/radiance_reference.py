"""An independent ground truth for camera images of a semi-infinite medium under a pencil
beam: the exitant *radiance* straight up (along the surface normal) as a function of the
distance from the beam, by a photon walk with a collision (next-event) estimator.

`sssjax.reference` tallies exitance (all exit directions); a camera sees radiance in one
direction, so the volumetric renderer is compared with this instead. Photons enter at the
origin along the refracted beam (normal incidence), take exact free flights, scatter with
Henyey-Greenstein, are split by the exact Fresnel reflectance at the surface and absorbed by
weight (implicit capture, Russian roulette). At every collision the scattered intensity
towards `+z`, `w alpha p(cos) exp(-sigma_t |z|)`, leaves at the point above it with the
transmittance `F_t(0) / eta^2` (radiance is compressed by `1 / eta^2` leaving the denser
medium) and is scored in that radial bin, per unit area. Per unit incident power; the
single-scattering part (the first collision) is reported separately.

Shares no code with `sssjax.transport` beyond the Fresnel and HG formulas.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from sssjax.dipole import fresnel_reflectance, hg_phase


def _hg_cos(u, g):
    if abs(g) < 1e-3:
        return 1.0 - 2.0 * u
    f = (1.0 - g * g) / (1.0 - g + 2.0 * g * u)
    return jnp.clip((1.0 + g * g - f * f) / (2.0 * g), -1.0, 1.0)


# a long-running walk: full LLVM optimisation whatever the suite's XLA_FLAGS (its O0 ran
# this 3.5x slower; see tests/conftest.py)
@functools.partial(
    jax.jit,
    static_argnames=("pool", "n_bins", "g", "max_steps"),
    compiler_options={"xla_backend_optimization_level": 3},
)
def _run(key, sigma_t, albedo, inv_eta, t_exit, edges, *, pool, n_bins, g, max_steps):
    z0 = jnp.zeros(pool)
    st = (z0, z0, z0, z0, z0, -jnp.ones(pool), jnp.ones(pool), jnp.zeros(pool, jnp.int32))
    tab = jnp.zeros((2, n_bins))

    def cond(c):
        i, st, tab = c
        return (i < max_steps) & jnp.any(st[6] > 0)

    def body(c):
        i, (x, y, z, dx, dy, dz, w, ns), tab = c
        u = jax.random.uniform(jax.random.fold_in(key, i), (5, pool))
        alive = w > 0
        s = -jnp.log1p(-u[0]) / sigma_t
        up = dz > 0
        t_s = jnp.where(up, -z / jnp.where(up, dz, 1.0), jnp.inf)
        hit = alive & (s >= t_s)
        coll = alive & ~hit
        step = jnp.where(hit, t_s, s)
        x, y = x + step * dx, y + step * dy
        z = jnp.where(hit, 0.0, jnp.minimum(z + step * dz, 0.0))
        F = fresnel_reflectance(dz, inv_eta)
        w = jnp.where(hit, w * F, w)
        dz = jnp.where(hit, -dz, dz)
        # collision: score the radiance sent straight up, then scatter
        w_after = w * albedo
        score = w_after * hg_phase(dz, g) * jnp.exp(sigma_t * z) * t_exit
        r = jnp.sqrt(x * x + y * y)
        b = jnp.clip(jnp.searchsorted(edges, r, side="right") - 1, 0, n_bins)
        ok = coll & (r < edges[-1])
        first = (ns == 0).astype(jnp.int32)
        tab = tab.at[0, jnp.where(ok, b, 0)].add(jnp.where(ok, score, 0.0))
        tab = tab.at[1, jnp.where(ok, b, 0)].add(jnp.where(ok & (first == 1), score, 0.0))
        w = jnp.where(coll, w_after, w)
        ns = ns + coll.astype(jnp.int32)
        ct = _hg_cos(u[1], g)
        phi = 2 * jnp.pi * u[2]
        # rotate (dx, dy, dz) by (ct, phi)
        sign = jnp.where(dz >= 0, 1.0, -1.0)
        a = -1.0 / (sign + dz)
        bb = dx * dy * a
        t = (1.0 + sign * dx * dx * a, sign * bb, -sign * dx)
        q = (bb, sign + dy * dy * a, -dy)
        st_ = jnp.sqrt(jnp.maximum(1 - ct * ct, 0.0))
        cp, sp = st_ * jnp.cos(phi), st_ * jnp.sin(phi)
        nx = cp * t[0] + sp * q[0] + ct * dx
        ny = cp * t[1] + sp * q[1] + ct * dy
        nz = cp * t[2] + sp * q[2] + ct * dz
        inv = jax.lax.rsqrt(nx * nx + ny * ny + nz * nz)
        dx = jnp.where(coll, nx * inv, dx)
        dy = jnp.where(coll, ny * inv, dy)
        dz = jnp.where(coll, nz * inv, dz)
        # roulette
        low = alive & (w < 0.05)
        surv = u[3] * 0.05 < w
        w = jnp.where(low, jnp.where(surv, 0.05, 0.0), w)
        return i + 1, (x, y, z, dx, dy, dz, w, ns), tab

    _, _, tab = jax.lax.while_loop(cond, body, (0, st, tab))
    return tab


def radiance_profile(
    sigma_a: float,
    sigma_s: float,
    g: float,
    eta: float,
    edges: np.ndarray,
    n_photons: int = 400_000,
    seed: int = 0,
    n_batches: int = 20,
) -> dict:
    """Radiance leaving along the normal, per unit incident power (mm^-2 sr^-1), in the
    radial bins `edges` (mm): `L`, `L_single`, and their batch standard errors."""
    sigma_t = sigma_a + sigma_s
    edges = np.asarray(edges, np.float64)
    n_bins = edges.size - 1
    pool = -(-n_photons // n_batches)
    t_exit = (1.0 - float(fresnel_reflectance(1.0, 1.0 / eta))) / eta**2
    t_in = 1.0 - float(fresnel_reflectance(1.0, eta))
    area = np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    per = []
    for b in range(n_batches):
        tab = _run(
            jax.random.key(seed * 1000 + b),
            sigma_t,
            sigma_s / sigma_t,
            1.0 / eta,
            t_exit,
            jnp.asarray(edges),
            pool=pool,
            n_bins=n_bins,
            g=float(g),
            max_steps=200_000,
        )
        per.append(np.asarray(tab, np.float64)[:, :n_bins] * t_in / pool / area)
    per = np.array(per)  # (batches, 2, bins)
    mean = per.mean(0)
    se = per.std(0, ddof=1) / np.sqrt(n_batches)
    return dict(L=mean[0], L_single=mean[1], L_se=se[0], L_single_se=se[1])
