"""The irradiance cloud of the diffusion transport: where light enters translucent objects.

Each translucent object gets `N` stratified, area-weighted surface points carrying their
shadow-tested, Fresnel-transmitted irradiance `E_i` (soft shadows included); each beam
light gets stratified rays from its source disc, each carrying its share of the power to
where it enters an object (Fresnel transmittance included). The cloud is traced once per
image and gathered by every pixel (`sssjax.transport.gather`). Lengths in mm.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._arrays import SceneArrays
from ..lights import direct_irradiance
from ..sampling import stratified_1d, stratified_2d
from ..scattering import fresnel_transmittance

__all__ = ["Cloud", "irradiance_cloud"]


class Cloud(eqx.Module):
    """Irradiance cloud on each translucent object (`No` objects, `N` points each)."""

    points: Float[Array, "No N 3"]
    normals: Float[Array, "No N 3"]
    irradiance: Float[Array, "No N 3"]  # transmitted into the medium: int F_t L cos dw
    area: Float[Array, " No"]  # area per point, mm^2
    # beam lights: where each of `Nb` beam rays enters the object and the power it carries
    # into the medium (W, Fresnel transmittance included; zero if it hit something else)
    beam_points: Float[Array, "No Nb 3"]
    beam_flux: Float[Array, "No Nb 3"]


def irradiance_cloud(arrays: SceneArrays, key: PRNGKeyArray, n: int, n_beam: int) -> Cloud:
    """Sample the irradiance cloud of every translucent object: `n` points per object,
    `n_beam` rays per beam light."""
    nl = arrays.render.light_samples
    lights = arrays.lights
    eta_obj = arrays.object_eta()
    pts, nrm, irr, area = [], [], [], []
    for j, i in enumerate(arrays.tobj_shape):
        k1, k2, k3 = jax.random.split(jax.random.fold_in(key, j), 3)
        u2 = stratified_2d(k1, n)
        u1 = stratified_1d(k2, n)
        p, nn = arrays.shapes[i].sample(jnp.concatenate([u2, u1[:, None]], axis=-1))
        ul = stratified_2d(k3, nl * nl, (n,))
        E = direct_irradiance(
            lights,
            p,
            nn,
            ul,
            arrays.occluded,
            transmit=lambda c, eta=eta_obj[j]: fresnel_transmittance(c, eta),
        )
        pts.append(p)
        nrm.append(nn)
        irr.append(E)
        area.append(arrays.tobj_area[j] / n)
    bp, bf = _beam_cloud(arrays, jax.random.fold_in(key, 7919), n_beam)
    if not pts:
        z = jnp.zeros((0, n, 3))
        return Cloud(z, z, z, jnp.zeros((0,)), bp, bf)
    return Cloud(jnp.stack(pts), jnp.stack(nrm), jnp.stack(irr), jnp.asarray(area), bp, bf)


def _beam_cloud(arrays: SceneArrays, key: PRNGKeyArray, nb: int):
    """Entry points and carried power of `nb` stratified rays per beam light, cast from the
    beam's source disc: `(No, n_beam * nb, 3)` each. Each ray carries `P / nb`; where it
    enters translucent object `j` that power times the Fresnel transmittance enters the
    medium. Unlike the uniform cloud this resolves a beam much narrower than the cloud
    spacing exactly (Jensen's point-illumination measurement)."""
    lights = arrays.lights
    No, L = arrays.n_objects, lights.n_beam
    if L == 0:
        z = jnp.zeros((No, 0, 3))
        return z, z
    pts, flux = [], []
    for k in range(L):
        u = stratified_2d(jax.random.fold_in(key, k), nb)
        e1, e2 = lights.beam_frame(k)
        rho = lights.beam_radius[k] * jnp.sqrt(u[:, 0])
        phi = 2.0 * jnp.pi * u[:, 1]
        d = lights.beam_dir[k]
        o = lights.beam_origin[k] + rho[:, None] * (
            jnp.cos(phi)[:, None] * e1 + jnp.sin(phi)[:, None] * e2
        )
        t, n, sid = arrays.intersect(o, jnp.broadcast_to(d, o.shape))
        x = o + jnp.where(jnp.isfinite(t), t, 0.0)[:, None] * d
        cos = -(n @ d)
        p_obj, f_obj = [], []
        for i in arrays.tobj_shape:
            on = (sid == i) & (cos > 0)
            Ft = fresnel_transmittance(jnp.where(on, cos, 1.0), arrays.eta[i])
            Phi = (Ft / nb)[:, None] * lights.beam_power[k]
            f_obj.append(jnp.where(on[:, None], Phi, 0.0))
            p_obj.append(x)
        pts.append(jnp.stack(p_obj))
        flux.append(jnp.stack(f_obj))
    return jnp.concatenate(pts, axis=1), jnp.concatenate(flux, axis=1)
