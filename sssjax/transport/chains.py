"""Camera rays and their specular chains (the diffusion transport's first phase).

Each camera sample follows mirrors and the Fresnel reflection of translucent boundaries up
to `[render] max_depth` bounces; it picks up emitters and the background it sees, direct
light on diffuse surfaces (soft shadows by stratified area-light sampling, beams), and at
its first translucent hit `x_o` the per-sample state ("slot") the subsurface terms start
from: where it is, the refracted view direction, the exit cosine, the object, the path
throughput and the Fresnel-transmitted irradiance `E(x_o)` (the dipole's near field).

Bounces past the camera's run only on the rays still alive (packed, in quarter-block
chunks, none when no ray is left): after the first hit most rays have ended.
Lengths in mm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, PRNGKeyArray

from .._arrays import EPS, MaterialKind, SceneArrays
from ..camera import camera_rays
from ..lights import beam_irradiance, direct_irradiance
from ..sampling import stratified_2d
from ..scattering import fresnel_reflectance, fresnel_transmittance, refract
from ._packing import step_alive
from ._record import NO_RECORD, Recorder

__all__ = ["SLOT_FIELDS", "chain_block"]

# per-sample state at the first translucent vertex of each path, output of the chains
SLOT_FIELDS = ("have", "xo", "din", "cos_o", "tobj", "T_slot", "E_o")
# bounces past the first run on the alive rays, packed, in chunks of 1/_BOUNCE_CHUNKS of the block
_BOUNCE_CHUNKS = 4


def chain_block(
    arrays: SceneArrays,
    pixels: Array,
    key: PRNGKeyArray,
    *,
    subsurface: bool,
    rec: Recorder = NO_RECORD,
) -> tuple[Array, dict]:
    """Trace `pixels` (flat indices, fixed block size) with `spp` samples each.

    **Arguments:** `subsurface`: record each sample's first translucent hit (SSS is on).

    **Returns:** `(base (P, 3), slots)`: `slots` maps `SLOT_FIELDS` to `(P, spp, ...)`
    arrays describing each sample's first translucent hit (`have` False where none).
    """
    S = arrays.render.spp
    P = pixels.shape[0]
    M = P * S
    k_cam, k_chain = jax.random.split(key)
    o, d = camera_rays(arrays.camera, pixels, stratified_2d(k_cam, S, (P,)))
    st = dict(
        o=o.reshape(M, 3),
        d=d.reshape(M, 3),
        T=jnp.ones((M, 3)),
        alive=jnp.ones(M, bool),
        base=jnp.zeros((M, 3)),
        have=jnp.zeros(M, bool),
        xo=jnp.zeros((M, 3)),
        din=jnp.zeros((M, 3)),
        cos_o=jnp.zeros(M),
        tobj=jnp.zeros(M, jnp.int32),
        T_slot=jnp.zeros((M, 3)),
        E_o=jnp.zeros((M, 3)),
    )
    lights = arrays.lights

    def bounce(depth, st, ul):
        return _bounce(arrays, lights, depth, st, ul, subsurface, rec)

    st = bounce(0, st, _light_u(arrays, k_chain, 0, M))
    max_depth = arrays.render.max_depth
    if rec.active:
        # recording runs eagerly: every bounce at full width, so the hooks see every ray
        for depth in range(1, max_depth + 1):
            st = bounce(depth, st, _light_u(arrays, k_chain, depth, M))
    elif max_depth > 0:
        st = jax.lax.fori_loop(
            1, max_depth + 1, lambda dep, s: _bounce_alive(arrays, bounce, dep, s, k_chain), st
        )
    base = st["base"].reshape(P, S, 3).mean(axis=1)
    slot = {f: st[f].reshape(P, S, *st[f].shape[1:]) for f in SLOT_FIELDS}
    return base, slot


def _light_u(arrays: SceneArrays, k_chain, depth, M):
    """The stratified area-light samples of bounce `depth` for all `M` rays of a block."""
    nl = arrays.render.light_samples
    return stratified_2d(jax.random.fold_in(k_chain, depth), nl * nl, (M,))


def _bounce_alive(arrays: SceneArrays, bounce, depth, st, k_chain):
    """One bounce past the camera's, run only on the rays still alive.

    After the first hit most rays have ended (on a diffuse surface, an emitter or the
    background), so the alive ones are packed to the front and bounced in chunks of
    `1/_BOUNCE_CHUNKS` of the block, only as many chunks as hold them (none when no ray is
    left), then scattered back: the cost follows the rays that bounce, not the block, and
    one chunk width compiles one copy of the bounce. The packing keeps each ray's own
    random numbers, so the image is that of the unpacked bounce.
    """
    M = st["alive"].shape[0]
    ul = _light_u(arrays, k_chain, depth, M)
    C = max(-(-M // _BOUNCE_CHUNKS), 1)

    def step(sub, idx):
        return bounce(depth, sub, jnp.take(ul, idx, axis=0, mode="fill", fill_value=0))

    return step_alive(st, C, step)


def _bounce(arrays: SceneArrays, lights, depth, st, ul, subsurface: bool, rec: Recorder):
    """Advance every ray of `st` by one hit: emitters and background it sees, direct
    light on diffuse surfaces, the first translucent hit's slot, and the specular
    continuation (mirror, or the Fresnel reflection of a translucent boundary)."""
    o, d, T, alive, base = st["o"], st["d"], st["T"], st["alive"], st["base"]
    slot = {f: st[f] for f in SLOT_FIELDS}
    # rays that escape see the background and the environment light
    bg = jnp.asarray(arrays.render.background, dtype=float) + lights.environment
    kind = jnp.asarray(arrays.kind, dtype=jnp.int32)
    tobj_of = np.full(len(arrays.kind), -1, np.int32)  # translucent object index per shape
    tobj_of[list(arrays.tobj_shape)] = np.arange(arrays.n_objects)
    tobj_of = jnp.asarray(tobj_of)
    t, n, sid = arrays.intersect(o, d)
    tl, rad = lights.intersect(o, d, t)
    hit_light = alive & (tl < t)
    base = base + jnp.where(hit_light[:, None], T * rad, 0.0)
    hit = alive & ~hit_light & (sid >= 0)
    miss = alive & ~hit_light & (sid < 0)
    base = base + jnp.where(miss[:, None], T * bg, 0.0)
    sidc = jnp.maximum(sid, 0)
    k = jnp.where(hit, kind[sidc], -1)
    x = o + jnp.where(hit, t, 0.0)[:, None] * d
    cos = -jnp.sum(d * n, axis=-1)
    ns = jnp.where((cos >= 0)[:, None], n, -n)  # normal facing the ray
    is_t = (k == MaterialKind.TRANSLUCENT) & (cos > 0)
    eta = arrays.eta[sidc]
    rec.chain(depth, o, d, x, tl, alive, hit_light, hit, k, is_t & ~slot["have"])
    E = None
    if arrays.has_diffuse or subsurface:
        # one set of shadow rays serves both: plain irradiance on diffuse surfaces,
        # Fresnel-transmitted irradiance E(x_o) (the dipole's near field) on
        # translucent ones
        def transmit(c, is_t=is_t, eta=eta):
            # c is (M,) for point lights and (M, strata) for area lights
            shape = (-1,) + (1,) * (c.ndim - 1)
            return jnp.where(is_t.reshape(shape), fresnel_transmittance(c, eta.reshape(shape)), 1.0)

        def occluded(o_, d_, t_max):
            return arrays.occluded(o_, d_, t_max, rec)

        E = direct_irradiance(lights, x, ns, ul, occluded, transmit)
        is_d = (k == MaterialKind.DIFFUSE)[:, None]
        E_d = E
        if lights.n_beam and arrays.has_diffuse:
            E_d = E + beam_irradiance(lights, x, ns, occluded)
        base = base + jnp.where(is_d, T * arrays.albedo[sidc] / jnp.pi * E_d, 0.0)
    Fr = fresnel_reflectance(cos, eta)
    if subsurface:
        first = is_t & ~slot["have"]
        dr, _ = refract(d, n, eta[:, None])
        new = dict(have=True, xo=x, din=dr, cos_o=cos, tobj=tobj_of[sidc], T_slot=T, E_o=E)
        for f, v in new.items():
            sel = first if slot[f].ndim == 1 else first[:, None]
            slot[f] = jnp.where(sel, v, slot[f])
    factor = jnp.where(
        (k == MaterialKind.MIRROR)[:, None],
        arrays.reflectance[sidc],
        jnp.where(is_t[:, None], Fr[:, None], 0.0),
    )
    return dict(
        o=x + EPS * ns,
        d=d - 2.0 * jnp.sum(d * ns, axis=-1, keepdims=True) * ns,
        T=T * factor,
        alive=(k == MaterialKind.MIRROR) | is_t,
        base=base,
        **slot,
    )
