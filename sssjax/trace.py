"""The geometric pass: everything about a render that does not depend on the media.

`trace` follows camera rays through their specular chains (mirrors, and the Fresnel
reflection of translucent boundaries), lights diffuse surfaces directly (soft shadows by
stratified area-light sampling), and for every first translucent hit `x_o` records what the
differentiable `shade` pass needs:

- **multiple scattering**: an irradiance cloud on each translucent object (area-weighted,
  stratified surface points `x_i` carrying `E_i A_i`, soft shadows and Fresnel transmittance
  included). Since `R_d` depends on geometry only through `r = |x_o - x_i|`, the gather
  `sum_i R_d(r_oi) E_i A_i` is stored per pixel as weights on fixed distance nodes
  (linear "hat" interpolation in `log(1 + r / r0)`); `shade` is then a small matrix product.
  Each of a pixel's `spp` samples gathers from a different stratified `1/spp` subset of the
  cloud (scaled by `spp`), so a pixel still sees the whole cloud at `1/spp` of the cost.
- **single scattering**: scatter distances `s'_o` along the refracted view ray, drawn from a
  fixed proposal (truncated exponential at the trace-time extinction, mixed with uniform, and
  clamped to the object's thickness found by an inside ray cast) whose exact pdf is stored, so
  `shade` re-weights by `integrand / pdf` for any coefficients; light connections through the
  boundary with shadow rays, the refracted-distance approximation inputs and phase cosines.

Lengths in mm. `eta` of each medium is geometry (it bends rays): it is fixed within a trace,
but it is an argument of the compiled functions (`SceneTracer.with_params`), so a fit of `eta`
re-traces at each value tried without recompiling.

Bounces past the camera's run only on the rays still alive (packed into a quarter of the
block when they fit, skipped when none is left): after the first hit most rays have ended.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from . import dipole
from .camera import camera_rays
from .lights import LightArrays, beam_irradiance, direct_irradiance
from .sampling import stratified_1d, stratified_2d
from .scattering import refract
from .scene import Scene
from .shapes import intersect_all

__all__ = ["Transport", "SSSBlock", "Cloud", "SceneTracer", "trace", "R0_MM", "refract"]

DIFFUSE, MIRROR, TRANSLUCENT = 0, 1, 2
EPS = 1e-3  # mm: ray offset off surfaces
R0_MM = 0.1  # mm: scale of the log distance nodes
_PROPOSAL_EXP = 0.75  # mixture weight of the exponential in the single-scattering proposal
# bounces past the first run on the alive rays packed into M / k slots (the narrowest that fits)
_BOUNCE_WIDTHS = (4, 1)


class Transport(eqx.Module):
    """The media-independent result of `trace` for a set of pixels.

    `base` holds everything that does not involve a medium (direct light on diffuse
    surfaces, emitters and background seen directly or in mirrors, Fresnel reflections of
    translucent boundaries). The subsurface terms exist only for the rows `t_rows` of pixels
    that see a translucent object. All radiometric fields are pixel averages (divided by spp).
    """

    pixels: Int[Array, " P"]
    base: Float[Array, "P 3"]
    t_rows: Int[Array, " Pt"]
    # channel-major, so that shading is one batched matrix-vector product per material
    # (10x faster on CPU than a trailing channel axis)
    ms_hist: Float[Array, "Mt 3 Pt B"]
    r_nodes: Float[Array, " B"]
    ss_mat: Int[Array, "Pt K"]
    ss_sp_o: Float[Array, "Pt K"]
    ss_sp_i: Float[Array, "Pt K"]
    ss_cos_i: Float[Array, "Pt K"]
    ss_cos_o: Float[Array, "Pt K"]
    ss_cos_phase: Float[Array, "Pt K"]
    ss_pdf: Float[Array, "Pt K"]
    ss_weight: Float[Array, "Pt K 3"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)
    materials: tuple = eqx.field(static=True)
    profile: str = eqx.field(static=True, default="dipole")  # `[sss] profile` of the scene

    @property
    def num_pixels(self) -> int:
        return self.pixels.shape[0]

    def sss_terms(self) -> SSSBlock:
        """The subsurface fields (rows `t_rows`) as an `SSSBlock`."""
        return SSSBlock(**{f: getattr(self, f) for f in SSS_FIELDS}, profile=self.profile)

    def translucent_pixels(self) -> Array:
        """Flat pixel indices of the rows with subsurface terms."""
        return self.pixels[self.t_rows]


class SSSBlock(eqx.Module):
    """Subsurface terms of a block of pixels (the translucent part of a `Transport`)."""

    ms_hist: Float[Array, "Mt 3 P B"]
    ss_mat: Int[Array, "P K"]
    ss_sp_o: Float[Array, "P K"]
    ss_sp_i: Float[Array, "P K"]
    ss_cos_i: Float[Array, "P K"]
    ss_cos_o: Float[Array, "P K"]
    ss_cos_phase: Float[Array, "P K"]
    ss_pdf: Float[Array, "P K"]
    ss_weight: Float[Array, "P K 3"]
    profile: str = eqx.field(static=True, default="dipole")  # as `Transport.profile`


SSS_FIELDS = (
    "ms_hist",
    "ss_mat",
    "ss_sp_o",
    "ss_sp_i",
    "ss_cos_i",
    "ss_cos_o",
    "ss_cos_phase",
    "ss_pdf",
    "ss_weight",
)  # the fields shared by `SSSBlock` and `Transport`


# per-sample state at the first translucent vertex of each path, output of the chain phase
SLOT_FIELDS = ("have", "xo", "din", "cos_o", "tobj", "T_slot", "E_o")


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


def disc_node_weights(r_nodes: np.ndarray, r0: float, du: float, R: float) -> np.ndarray:
    """Weights `w_b` with `sum_b w_b f(r_b) = int_0^R 2 pi r f(r) dr` for any `f` that is
    piecewise linear in `u = log(1 + r / r0)` between the nodes (the hat interpolation used
    for the cloud gather), computed by fine quadrature (float64)."""
    r = np.linspace(0.0, R, 200_001)
    u = np.log1p(r / r0) / du
    b0 = np.clip(np.floor(u).astype(int), 0, len(r_nodes) - 2)
    frac = np.clip(u - b0, 0.0, 1.0)
    g = 2 * np.pi * r
    dr = np.full_like(r, r[1] - r[0])
    dr[0] = dr[-1] = 0.5 * (r[1] - r[0])  # trapezoid rule
    w = np.zeros(len(r_nodes))
    np.add.at(w, b0, g * (1 - frac) * dr)
    np.add.at(w, b0 + 1, g * frac * dr)
    return w


def _unit(v):
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > 0, n, 1.0)


class SceneTracer:
    """Compiled geometric queries and the per-block `trace` of one scene (and its settings)."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self.shapes = [s.shape for s in scene.shapes]
        self.lights0 = LightArrays.from_scene(scene.lights)
        self.light_kinds = tuple(
            {"AreaLight": "area", "PointLight": "point", "BeamLight": "beam"}[type(lt).__name__]
            for lt in scene.lights
        )
        self._gain = None  # per-light emission factors being traced (`with_params`)
        mats = scene.materials
        self.tmat_names = tuple(scene.translucent_materials)
        kinds = {"diffuse": DIFFUSE, "mirror": MIRROR, "translucent": TRANSLUCENT}
        self.shape_kind = np.array([kinds[mats[s.material].type] for s in scene.shapes], np.int32)
        self.shape_albedo = np.array(
            [mats[s.material].albedo for s in scene.shapes] or np.zeros((0, 3))
        ).reshape(-1, 3)
        self.shape_refl = np.array(
            [mats[s.material].reflectance for s in scene.shapes] or np.zeros((0, 3))
        ).reshape(-1, 3)
        # translucent objects: shape indices, their material index (into tmat_names), eta
        self.tobj_shape = [i for i, s in enumerate(scene.shapes) if self.shape_kind[i] == 2]
        self.tobj_mat = np.array(
            [self.tmat_names.index(scene.shapes[i].material) for i in self.tobj_shape], np.int32
        )
        tob = np.full(len(scene.shapes), -1, np.int32)
        tob[self.tobj_shape] = np.arange(len(self.tobj_shape))
        self.shape_tobj = tob
        eta = np.ones(len(scene.shapes))
        lam = np.ones(max(len(self.tobj_shape), 1))
        for j, i in enumerate(self.tobj_shape):
            m = mats[scene.shapes[i].material].medium
            eta[i] = float(m.eta)
            lam[j] = float(np.mean(np.asarray(m.sigma_t)))
        self.eta0 = eta  # the scene's refractive index per shape (1 where not translucent)
        self._eta = None  # the index being traced: set only while a jitted method traces
        self.tobj_area = [float(self.shapes[i].area()) for i in self.tobj_shape]
        self.tobj_lambda = lam
        self.spp = scene.render.spp
        n = scene.sss.cloud_size
        self.cloud_n = int(math.ceil(n / self.spp) * self.spp)
        nb = scene.sss.beam_points
        self.beam_n = int(math.ceil(nb / self.spp) * self.spp)  # beam rays per beam
        self.bins = scene.sss.bins
        if self.tobj_shape:
            diag = max(
                float(np.linalg.norm(np.subtract(*self.shapes[i].bounds()[::-1])))
                for i in self.tobj_shape
            )
        else:
            diag = 1.0
        self.r_max = 1.01 * diag
        self.du = math.log1p(self.r_max / R0_MM) / (self.bins - 1)
        u = np.arange(self.bins) * self.du
        self.r_nodes = R0_MM * np.expm1(u)
        # near-field radius per object: two cloud spacings
        self.tobj_rnear = [2.0 * math.sqrt(a / self.cloud_n) for a in self.tobj_area]
        self.near_weights = np.stack(
            [disc_node_weights(self.r_nodes, R0_MM, self.du, R) for R in self.tobj_rnear]
            or [np.zeros(self.bins)]
        )
        self.sss_on = scene.sss.enabled and bool(self.tobj_shape)
        self.ss_on = self.sss_on and scene.sss.single_scattering
        # a `sssjax.raytree` recorder: set only on a tracer whose methods run eagerly (never
        # under jit); every hook below is skipped while it is None
        self._rec = None
        self._cloud_fn = jax.jit(functools.partial(self.with_params, self._cloud))
        self._chain_fn = jax.jit(functools.partial(self.with_params, self._chain_block))
        self._sss_fn = jax.jit(functools.partial(self.with_params, self._sss_block))

    # -- the refractive index and the lights' emission: arguments of the compiled functions --
    @property
    def shape_eta(self):
        """Refractive index per shape: the scene's, or the one being traced (`with_params`)."""
        return self.eta0 if self._eta is None else self._eta

    @property
    def lights(self) -> LightArrays:
        """The scene's lights, each one's emission times the factor being traced."""
        return (
            self.lights0
            if self._gain is None
            else self.lights0.scaled(self._gain, self.light_kinds)
        )

    def eta_for(self, etas: dict | None = None) -> np.ndarray:
        """The per-shape index array with translucent materials' `eta` from `etas` (by
        material name; the scene's for the others)."""
        eta = np.array(self.eta0, dtype=np.float64)
        for i in self.tobj_shape:
            name = self.scene.shapes[i].material
            if etas and name in etas:
                eta[i] = float(etas[name])
        return eta

    def with_params(self, fn, *args, eta=None, gain=None):
        """Run `fn(*args)` with the per-shape index `eta` (default the scene's) and the
        per-light emission factors `gain` (default 1). The compiled methods take both as
        arguments, so a fit of `eta` re-traces without recompiling, and so does tracing one
        light alone (a fit of a light's intensity)."""
        prev = self._eta, self._gain
        self._eta = None if eta is None else jnp.asarray(eta, dtype=float)
        self._gain = None if gain is None else jnp.asarray(gain, dtype=float)
        try:
            return fn(*args)
        finally:
            self._eta, self._gain = prev

    # -- geometric queries ---------------------------------------------------------------
    def intersect(self, o, d, t_max=jnp.inf):
        """Nearest shape hit: `(t, n, shape_index)` over any batch shape."""
        o, d = jnp.broadcast_arrays(o, d)
        shp = o.shape[:-1]
        t, n, sid = intersect_all(
            self.shapes, o.reshape(-1, 3), d.reshape(-1, 3), EPS * 0.1, jnp.inf
        )
        t = jnp.where(t < t_max if np.ndim(t_max) == 0 else t < jnp.reshape(t_max, -1), t, jnp.inf)
        sid = jnp.where(jnp.isfinite(t), sid, -1)
        return t.reshape(shp), n.reshape(*shp, 3), sid.reshape(shp)

    def occluded(self, o, d, t_max):
        """Shadow ray: is there any shape between `o` and `o + t_max d`?"""
        t, _, _ = self.intersect(o, d)
        if self._rec is not None:
            self._rec.shadow(o, d, t, t_max)
        return t < t_max

    def intersect_object(self, j_obj, o, d):
        """Hit of the rays with translucent object `j_obj` (per ray), from inside or outside."""
        o, d = jnp.broadcast_arrays(o, d)
        shp = o.shape[:-1]
        o2, d2 = o.reshape(-1, 3), d.reshape(-1, 3)
        j2 = jnp.broadcast_to(j_obj, shp).reshape(-1)
        t = jnp.full(o2.shape[0], jnp.inf)
        n = jnp.zeros_like(o2)
        for j, i in enumerate(self.tobj_shape):
            tj, nj = self.shapes[i].intersect(o2, d2, EPS * 0.1, jnp.inf)
            sel = j2 == j
            t = jnp.where(sel, tj, t)
            n = jnp.where(sel[:, None], nj, n)
        return t.reshape(shp), n.reshape(*shp, 3)

    # -- the irradiance cloud ------------------------------------------------------------
    def cloud(self, key: PRNGKeyArray, eta=None, gain=None) -> Cloud:
        """Sample the irradiance cloud of every translucent object (`eta`: per-shape
        refractive index, default the scene's; `gain`: per-light emission factors)."""
        eta = self.eta_for() if eta is None else eta
        return self._cloud_fn(key, eta=eta, gain=self.gain_for(gain))

    def gain_for(self, gain=None) -> Array:
        """Per-light emission factors as the compiled functions take them (default 1)."""
        n = len(self.light_kinds)
        return jnp.ones(n) if gain is None else jnp.asarray(gain, dtype=float).reshape(n)

    def _cloud(self, key):
        n, nl = self.cloud_n, self.scene.render.light_samples
        pts, nrm, irr, area = [], [], [], []
        for j, i in enumerate(self.tobj_shape):
            kj = jax.random.fold_in(key, j)
            k1, k2, k3 = jax.random.split(kj, 3)
            u2 = stratified_2d(k1, n)
            u1 = stratified_1d(k2, n)
            p, nn = self.shapes[i].sample(jnp.concatenate([u2, u1[:, None]], axis=-1))
            eta = self.shape_eta[i]
            ul = stratified_2d(k3, nl * nl, (n,))
            E = direct_irradiance(
                self.lights,
                p,
                nn,
                ul,
                self.occluded,
                transmit=lambda c, eta=eta: dipole.fresnel_transmittance(c, eta),
            )
            pts.append(p)
            nrm.append(nn)
            irr.append(E)
            area.append(self.tobj_area[j] / n)
        bp, bf = self._beam_cloud(jax.random.fold_in(key, 7919))
        if not pts:
            z = jnp.zeros((0, n, 3))
            return Cloud(z, z, z, jnp.zeros((0,)), bp, bf)
        return Cloud(jnp.stack(pts), jnp.stack(nrm), jnp.stack(irr), jnp.asarray(area), bp, bf)

    def _beam_cloud(self, key):
        """Entry points and carried power of `beam_n` stratified rays per beam light, cast
        from the beam's source disc: `(No, n_beam * beam_n, 3)` each. Each ray carries
        `P / beam_n`; where it enters translucent object `j` that power times the Fresnel
        transmittance enters the medium. Unlike the uniform cloud this resolves a beam much
        narrower than the cloud spacing exactly (Jensen's point-illumination measurement)."""
        No, L, nb = len(self.tobj_shape), self.lights.n_beam, self.beam_n
        if L == 0:
            z = jnp.zeros((No, 0, 3))
            return z, z
        pts, flux = [], []
        for k in range(L):
            u = stratified_2d(jax.random.fold_in(key, k), nb)
            e1, e2 = self.lights.beam_frame(k)
            rho = self.lights.beam_radius[k] * jnp.sqrt(u[:, 0])
            phi = 2.0 * jnp.pi * u[:, 1]
            d = self.lights.beam_dir[k]
            o = self.lights.beam_origin[k] + rho[:, None] * (
                jnp.cos(phi)[:, None] * e1 + jnp.sin(phi)[:, None] * e2
            )
            t, n, sid = self.intersect(o, jnp.broadcast_to(d, o.shape))
            x = o + jnp.where(jnp.isfinite(t), t, 0.0)[:, None] * d
            cos = -(n @ d)
            p_obj, f_obj = [], []
            for i in self.tobj_shape:
                on = (sid == i) & (cos > 0)
                Ft = dipole.fresnel_transmittance(jnp.where(on, cos, 1.0), self.shape_eta[i])
                Phi = (Ft / nb)[:, None] * self.lights.beam_power[k]
                f_obj.append(jnp.where(on[:, None], Phi, 0.0))
                p_obj.append(x)
            pts.append(jnp.stack(p_obj))
            flux.append(jnp.stack(f_obj))
        return jnp.concatenate(pts, axis=1), jnp.concatenate(flux, axis=1)

    # -- phase 1: camera rays and their specular chains ----------------------------------
    def chain_block(self, pixels: Array, key: PRNGKeyArray):
        """Trace `pixels` (flat indices, fixed block size) with `spp` samples each.

        **Returns:** `(base (P, 3), slots)`: `slots` maps `SLOT_FIELDS` to `(P, spp, ...)`
        arrays describing each sample's first translucent hit (`have` False where none).
        """
        return self._chain_fn(pixels, key, eta=self.eta0, gain=self.gain_for())

    def _chain_block(self, pixels, key):
        sc = self.scene
        S = self.spp
        P = pixels.shape[0]
        M = P * S
        k_cam, k_chain = jax.random.split(key)
        o, d = camera_rays(sc.camera, pixels, stratified_2d(k_cam, S, (P,)))
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
        st = self._bounce(0, st, self._light_u(k_chain, 0, M))
        if self._rec is not None:
            # recording runs eagerly: every bounce at full width, so the hooks see every ray
            for depth in range(1, sc.render.max_depth + 1):
                st = self._bounce(depth, st, self._light_u(k_chain, depth, M))
        elif sc.render.max_depth > 0:
            st = jax.lax.fori_loop(
                1, sc.render.max_depth + 1, lambda dep, s: self._bounce_alive(dep, s, k_chain), st
            )
        base = st["base"].reshape(P, S, 3).mean(axis=1)
        slot = {f: st[f].reshape(P, S, *st[f].shape[1:]) for f in SLOT_FIELDS}
        return base, slot

    def _light_u(self, k_chain, depth, M):
        """The stratified area-light samples of bounce `depth` for all `M` rays of a block."""
        nl = self.scene.render.light_samples
        return stratified_2d(jax.random.fold_in(k_chain, depth), nl * nl, (M,))

    def _bounce_alive(self, depth, st, k_chain):
        """One bounce past the camera's, run only on the rays still alive.

        After the first hit most rays have ended (on a diffuse surface, an emitter or the
        background), so the alive ones are packed into the narrowest of `_BOUNCE_WIDTHS`
        that holds them (a block with none skips the bounce) and scattered back: the cost
        follows the rays that bounce, not the block. The packing keeps each ray's own random
        numbers, so the image is that of the unpacked bounce.
        """
        M = st["alive"].shape[0]
        ul = self._light_u(k_chain, depth, M)
        widths = sorted({max(-(-M // k), 1) for k in _BOUNCE_WIDTHS})

        def packed(width):
            def run(st):
                if width == M:
                    return self._bounce(depth, st, ul)
                idx = jnp.nonzero(st["alive"], size=width, fill_value=M)[0]
                sub = {
                    f: jnp.take(v, idx, axis=0, mode="fill", fill_value=0) for f, v in st.items()
                }
                sub = self._bounce(depth, sub, jnp.take(ul, idx, axis=0, mode="fill", fill_value=0))
                return {f: v.at[idx].set(sub[f], mode="drop") for f, v in st.items()}

            return run

        n_alive = jnp.sum(st["alive"])
        branch = jnp.where(
            n_alive == 0, 0, 1 + jnp.searchsorted(jnp.asarray(widths), n_alive, side="left")
        )
        return jax.lax.switch(branch, [lambda s: s] + [packed(w) for w in widths], st)

    def _bounce(self, depth, st, ul):
        """Advance every ray of `st` by one hit: emitters and background it sees, direct
        light on diffuse surfaces, the first translucent hit's slot, and the specular
        continuation (mirror, or the Fresnel reflection of a translucent boundary)."""
        sc = self.scene
        o, d, T, alive, base = st["o"], st["d"], st["T"], st["alive"], st["base"]
        slot = {f: st[f] for f in SLOT_FIELDS}
        bg = jnp.asarray(sc.render.background, dtype=float)
        kind = jnp.asarray(self.shape_kind)
        albedo = jnp.asarray(self.shape_albedo, dtype=float)
        refl = jnp.asarray(self.shape_refl, dtype=float)
        eta_s = jnp.asarray(self.shape_eta, dtype=float)
        tobj_of = jnp.asarray(self.shape_tobj)
        has_diffuse = bool(np.any(self.shape_kind == DIFFUSE))
        t, n, sid = self.intersect(o, d)
        tl, rad = self.lights.intersect(o, d, t)
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
        is_t = (k == TRANSLUCENT) & (cos > 0)
        eta = eta_s[sidc]
        if self._rec is not None:
            self._rec.chain(depth, o, d, x, tl, alive, hit_light, hit, k, is_t & ~slot["have"])
        E = None
        if has_diffuse or self.sss_on:
            # one set of shadow rays serves both: plain irradiance on diffuse surfaces,
            # Fresnel-transmitted irradiance E(x_o) (the dipole's near field) on
            # translucent ones
            def transmit(c, is_t=is_t, eta=eta):
                # c is (M,) for point lights and (M, strata) for area lights
                shape = (-1,) + (1,) * (c.ndim - 1)
                return jnp.where(
                    is_t.reshape(shape),
                    dipole.fresnel_transmittance(c, eta.reshape(shape)),
                    1.0,
                )

            E = direct_irradiance(self.lights, x, ns, ul, self.occluded, transmit)
            is_d = (k == DIFFUSE)[:, None]
            E_d = E
            if self.lights.n_beam and has_diffuse:
                E_d = E + beam_irradiance(self.lights, x, ns, self.occluded)
            base = base + jnp.where(is_d, T * albedo[sidc] / jnp.pi * E_d, 0.0)
        Fr = dipole.fresnel_reflectance(cos, eta)
        if self.sss_on:
            first = is_t & ~slot["have"]
            dr, _ = refract(d, n, eta[:, None])
            new = dict(have=True, xo=x, din=dr, cos_o=cos, tobj=tobj_of[sidc], T_slot=T, E_o=E)
            for f, v in new.items():
                sel = first if slot[f].ndim == 1 else first[:, None]
                slot[f] = jnp.where(sel, v, slot[f])
        factor = jnp.where(
            (k == MIRROR)[:, None], refl[sidc], jnp.where(is_t[:, None], Fr[:, None], 0.0)
        )
        return dict(
            o=x + EPS * ns,
            d=d - 2.0 * jnp.sum(d * ns, axis=-1, keepdims=True) * ns,
            T=T * factor,
            alive=(k == MIRROR) | is_t,
            base=base,
            **slot,
        )

    # -- phase 2: subsurface terms of the pixels that see a translucent object -------------
    @property
    def ss_per_sample(self) -> int:
        """Single-scattering records per camera sample (samples x lights)."""
        if not self.ss_on:
            return 0
        return self.scene.sss.single_samples * (self.lights.n_area + self.lights.n_point)

    def sss_block(self, slots: dict, key: PRNGKeyArray, cloud: Cloud) -> SSSBlock:
        """Subsurface terms for a block of pixels given their `slots` (`(P, spp, ...)`)."""
        return self._sss_fn(slots, key, cloud, eta=self.eta0, gain=self.gain_for())

    def _sss_block(self, slots, key, cloud):
        P, S = slots["have"].shape
        M = P * S
        s = {f: v.reshape(M, *v.shape[2:]) for f, v in slots.items()}
        k_ms, key = jax.random.split(key)
        if self.scene.sss.strategy == "cloud":
            hist = self._gather_ms(
                cloud, s["have"], s["xo"], s["cos_o"], s["tobj"], s["T_slot"], s["E_o"], P, S
            )
        else:
            hist = self._sample_ms(
                k_ms, s["have"], s["xo"], s["cos_o"], s["tobj"], s["T_slot"], P, S
            )
        if self.lights.n_beam:
            hist = hist + self._gather_beams(
                cloud, s["have"], s["xo"], s["cos_o"], s["tobj"], s["T_slot"], P, S
            )
        K = self.ss_per_sample
        if K > 0:
            ss = self._single_scatter(
                key, s["have"], s["xo"], s["din"], s["cos_o"], s["tobj"], s["T_slot"], P, S
            )
        else:
            ss = dict(
                mat=jnp.full((P, 0), -1, jnp.int32),
                **{f: jnp.zeros((P, 0)) for f in ("sp_o", "sp_i", "cos_i", "cos_o", "phase")},
                pdf=jnp.ones((P, 0)),
                weight=jnp.zeros((P, 0, 3)),
            )
        return SSSBlock(
            ms_hist=jnp.transpose(hist, (0, 3, 1, 2)),
            ss_mat=ss["mat"],
            ss_sp_o=ss["sp_o"],
            ss_sp_i=ss["sp_i"],
            ss_cos_i=ss["cos_i"],
            ss_cos_o=ss["cos_o"],
            ss_cos_phase=ss["phase"],
            ss_pdf=ss["pdf"],
            ss_weight=ss["weight"],
        )

    def _gather_ms(self, cloud, have, xo, cos_o, tobj, T_slot, E_o, P, S):
        """Distance-node weights of `F_t(cos_o)/pi int R_d(|x_o - x|) E(x) dA(x)`, per pixel.

        Far field (`r >= R_near`): the cloud sum `sum_i R_d(r_oi) E_i A_i`. Near field: the
        surface is taken as a flat disc of radius `R_near` lit by `E(x_o)`, integrated exactly
        on the nodes (`near_weights`). This removes the blotches a point cloud leaves where
        `R_d` is steepest, at the cost of assuming flatness within `R_near` (about two cloud
        spacings).
        """
        Mt, B = len(self.tmat_names), self.bins
        p, r, E, w_o, Ft_o = self._subsets(
            cloud.points, cloud.irradiance, have, xo, cos_o, tobj, T_slot, P, S
        )
        # spp subsets of 1/spp of the cloud each: scale by spp, then average over spp -> 1
        w_o = w_o * cloud.area[tobj][:, None] / S  # area per point; / S for the pixel mean
        far = (r >= jnp.asarray(self.tobj_rnear, dtype=float)[tobj][:, None])[..., None]
        w = jnp.where(far, w_o[:, None, :] * E * S, 0.0)  # (M, n_sub, 3)
        if self._rec is not None:
            self._rec.points(p, w, have)
        hist = self._bin(r, w, tobj, P, S)
        mat = jnp.asarray(self.tobj_mat)[tobj][:, None]
        # near field: (T F_t / pi) E(x_o) int_{r < R_near} 2 pi r R_d(r) dr, on the nodes
        w_near = jnp.where(have[:, None], T_slot * E_o * (Ft_o / jnp.pi)[:, None], 0.0) / S
        nw = jnp.asarray(self.near_weights, dtype=float)[tobj]  # (M, B)
        onehot = (mat == jnp.arange(Mt)).astype(w_near.dtype)  # (M, Mt)
        near = jnp.einsum(
            "psb,psc,psm->mpbc",
            nw.reshape(P, S, B),
            w_near.reshape(P, S, 3),
            onehot.reshape(P, S, Mt),
        )
        return hist + near

    def _subsets(self, points, values, have, xo, cos_o, tobj, T_slot, P, S):
        """Each sample's `1/spp` subset of per-object source points (`points`, `values`:
        `(No, N, 3)`): sample `s` of a pixel takes points `s, s + S, s + 2S, ...` of its
        object. **Returns:** `p (P, S, n, 3)`, distances `r (M, n)`, `values (M, n, 3)`, the
        exit factor `T F_t(cos_o) / pi (M, 3)` (zero where `have` is False) and `F_t`."""
        M = P * S
        n_sub = points.shape[1] // S
        # broadcasting over pixels and selecting the object with `where` avoids a gather
        # indexed by data (which XLA on CPU does slowly)
        pts = points.reshape(-1, n_sub, S, 3).transpose(0, 2, 1, 3)
        val = values.reshape(-1, n_sub, S, 3).transpose(0, 2, 1, 3)
        tob = tobj.reshape(P, S, 1, 1)
        p, v = pts[0][None], val[0][None]
        for jo in range(1, pts.shape[0]):
            p = jnp.where(tob == jo, pts[jo][None], p)
            v = jnp.where(tob == jo, val[jo][None], v)
        r = jnp.linalg.norm(p - xo.reshape(P, S, 1, 3), axis=-1).reshape(M, n_sub)
        v = jnp.broadcast_to(v, (P, S, n_sub, 3)).reshape(M, n_sub, 3)
        eta = jnp.asarray(self.shape_eta, dtype=float)[jnp.asarray(self.tobj_shape)][tobj]
        Ft_o = dipole.fresnel_transmittance(cos_o, eta)
        w_o = jnp.where(have, 1.0, 0.0)[:, None] * T_slot * (Ft_o / jnp.pi)[:, None]
        return p, r, v, w_o, Ft_o

    def _gather_beams(self, cloud, have, xo, cos_o, tobj, T_slot, P, S):
        """Distance-node weights of `F_t(cos_o)/pi sum_i R_d(|x_o - x_i|) Phi_i` over the
        beam rays (power `Phi_i` entering at `x_i`), each sample gathering a stratified
        `1/spp` subset (scaled by spp). No near-field disc: the beam points are the source."""
        p, r, Phi, w_o, _ = self._subsets(
            cloud.beam_points, cloud.beam_flux, have, xo, cos_o, tobj, T_slot, P, S
        )
        w = w_o[:, None, :] * Phi  # (M, n_sub, 3): x S for the subset, / S for the mean
        if self._rec is not None:
            self._rec.points(p, w, have)
        return self._bin(r, w, tobj, P, S)

    def _bin(self, r, w, tobj, P, S):
        """Scatter weights `w (M, n, 3)` at distances `r (M, n)` onto the distance nodes of
        each sample's pixel and material (linear hat interpolation in `log(1 + r / r0)`)."""
        Mt, B = len(self.tmat_names), self.bins
        u = jnp.log1p(r / R0_MM) / self.du
        b0 = jnp.clip(jnp.floor(u), 0, B - 2).astype(jnp.int32)
        frac = jnp.clip(u - b0, 0.0, 1.0)[..., None]
        pix = jnp.repeat(jnp.arange(P), S)[:, None]
        mat = jnp.asarray(self.tobj_mat)[tobj][:, None]
        flat = (mat * P + pix) * B + b0
        hist = jnp.zeros((Mt * P * B, 3), w.dtype)
        hist = hist.at[flat.ravel()].add((w * (1 - frac)).reshape(-1, 3))
        hist = hist.at[(flat + 1).ravel()].add((w * frac).reshape(-1, 3))
        return hist.reshape(Mt, P, B, 3)

    def _sample_ms(self, key, have, xo, cos_o, tobj, T_slot, P, S):
        """Per-pixel Monte Carlo estimate of the dipole gather (strategies `uniform`,
        `within`, `annulus`): `samples` surface points per camera sample, each with its own
        shadow-tested irradiance.

        Each of the `samples` slots draws up to `tries` candidates uniformly by area over the
        object (pdf `1/A`) and keeps the first inside the strategy's region (`uniform`: the
        whole surface; `within`: `r < radius`; `annulus`: `inner <= r < outer`). The estimator
        `A (n_accepted / tries) f(x_first accepted)` is exactly unbiased for the integral over
        the region (given `n_accepted`, the accepted candidates are i.i.d. uniform on the
        region), so only one irradiance evaluation per slot is needed; a slot with no accepted
        candidate contributes zero. `within` and `annulus` deliberately leave out the rest of
        the surface, as in the original report.
        """
        cfg = self.scene.sss
        M = P * S
        K = cfg.samples
        T = 1 if cfg.strategy == "uniform" else cfg.tries
        nl = self.scene.render.light_samples
        k1, k2, k3 = jax.random.split(key, 3)
        u2 = stratified_2d(k1, K * T, (M,))  # stratified over the slots x tries of a sample
        u1 = stratified_1d(k2, K * T, (M,))
        u = jnp.concatenate([u2, u1[..., None]], axis=-1).reshape(M, K, T, 3)
        p = jnp.zeros((M, K, T, 3))
        n = jnp.zeros((M, K, T, 3))
        area = jnp.zeros(M)
        eta = jnp.ones(M)
        for j, i in enumerate(self.tobj_shape):
            pj, nj = self.shapes[i].sample(u)
            sel = (tobj == j)[:, None, None, None]
            p = jnp.where(sel, pj, p)
            n = jnp.where(sel, nj, n)
            area = jnp.where(tobj == j, self.tobj_area[j], area)
            eta = jnp.where(tobj == j, self.shape_eta[i], eta)
        r = jnp.linalg.norm(p - xo[:, None, None, :], axis=-1)  # (M, K, T)
        if cfg.strategy == "within":
            acc = r < cfg.radius
        elif cfg.strategy == "annulus":
            acc = (r >= cfg.inner) & (r < cfg.outer)
        else:
            acc = jnp.ones(r.shape, bool)
        n_acc = jnp.sum(acc, axis=-1)  # (M, K)
        first = jnp.argmax(acc, axis=-1)
        take = lambda a: jnp.take_along_axis(a, first[..., None, None], axis=2)[:, :, 0]  # noqa: E731
        p1, n1 = take(p), take(n)
        r1 = jnp.take_along_axis(r, first[..., None], axis=2)[..., 0]
        ul = stratified_2d(k3, nl * nl, (M, K))
        if self._rec is not None:
            self._rec.dipole(xo, p1, have)

        def transmit(c):
            return dipole.fresnel_transmittance(c, eta.reshape((-1,) + (1,) * (c.ndim - 1)))

        E = direct_irradiance(self.lights, p1, n1, ul, self.occluded, transmit)  # (M, K, 3)
        Ft_o = dipole.fresnel_transmittance(cos_o, eta)
        w_o = jnp.where(have, 1.0, 0.0)[:, None] * T_slot * (Ft_o / jnp.pi)[:, None]
        scale = area[:, None] * n_acc / (T * K * S)  # (M, K)
        w = w_o[:, None, :] * E * scale[..., None]
        if self._rec is not None:
            self._rec.points(p1, w, have)
        return self._bin(r1, w, tobj, P, S)

    def _single_scatter(self, key, have, xo, din, cos_o, tobj, T_slot, P, S):
        """Scatter points along the refracted view ray, connected to every light."""
        M = P * S
        n_ss = self.scene.sss.single_samples
        k1, k2, k3, k4 = jax.random.split(key, 4)
        tobj_shape = jnp.asarray(self.tobj_shape)
        eta = jnp.asarray(self.shape_eta, dtype=float)[tobj_shape][tobj][:, None]  # (M,1)
        lam = jnp.asarray(self.tobj_lambda, dtype=float)[tobj][:, None]
        # thickness along the refracted ray
        thick, _ = self.intersect_object(tobj, xo - EPS * 0.5 * din, din)
        thick = jnp.where(have & jnp.isfinite(thick), thick, 0.0)[:, None]  # (M,1)
        ok_thick = thick > 0
        th = jnp.where(ok_thick, thick, 1.0)
        # proposal: truncated exponential (rate lam) on [0, th] mixed with uniform
        u_sel = stratified_1d(k1, n_ss, (M,))
        u_s = jax.random.uniform(k2, (M, n_ss))
        use_exp = u_sel < _PROPOSAL_EXP
        norm = -jnp.expm1(-lam * th)
        s_exp = -jnp.log1p(-u_s * norm) / lam
        s_uni = u_s * th
        sp_o = jnp.where(use_exp, s_exp, s_uni)
        pdf = _PROPOSAL_EXP * lam * jnp.exp(-lam * sp_o) / norm + (1 - _PROPOSAL_EXP) / th
        xs = xo[:, None, :] + sp_o[..., None] * din[:, None, :]  # (M, n_ss, 3)
        if self._rec is not None:
            self._rec.ss_paths(xo, xs, have)
        # light samples: one stratified point per scatter sample on each area light
        targets = []
        for k in range(self.lights.n_area):
            ul = stratified_2d(jax.random.fold_in(k3, k), n_ss, (M,))
            y = (
                self.lights.corner[k]
                + ul[..., 0:1] * self.lights.edge_u[k]
                + ul[..., 1:2] * self.lights.edge_v[k]
            )
            targets.append((y, k, "area"))
        for k in range(self.lights.n_point):
            y = jnp.broadcast_to(self.lights.position[k], (M, n_ss, 3))
            targets.append((y, k, "point"))
        out = {f: [] for f in ("sp_i", "cos_i", "phase", "weight", "sp_o", "pdf")}
        for y, k, kind in targets:
            w = _unit(y - xs)
            t_exit, n_i = self.intersect_object(jnp.broadcast_to(tobj[:, None], (M, n_ss)), xs, w)
            found = jnp.isfinite(t_exit)
            t_e = jnp.where(found, t_exit, 0.0)
            xi = xs + t_e[..., None] * w
            cos_i = jnp.sum(w * n_i, axis=-1)
            to_light = y - xi
            dist = jnp.linalg.norm(to_light, axis=-1)
            if self._rec is not None:
                self._rec.ss_exit(xs, xi)
            vis = ~self.occluded(xi + EPS * n_i, w, dist * (1 - 1e-4))
            prop_in, ok_r = refract(-w, n_i, eta[..., None])
            phase = jnp.sum(prop_in * -din[:, None, :], axis=-1)
            sp_i = dipole.refracted_distance(t_e, cos_i, eta)
            if kind == "area":
                cos_l = jnp.maximum(-(w @ self.lights.normal[k]), 0.0)
                Lg = self.lights.radiance[k] * (self.lights.area[k] * cos_l / dist**2)[..., None]
            else:
                Lg = self.lights.intensity[k] * (1.0 / dist**2)[..., None]
            valid = have[:, None] & ok_thick & found & (cos_i > 0) & vis & ok_r
            weight = jnp.where(valid[..., None], T_slot[:, None, :] * Lg, 0.0) / (n_ss * S)
            out["sp_i"].append(sp_i)
            out["cos_i"].append(cos_i)
            out["phase"].append(phase)
            out["weight"].append(weight)
            out["sp_o"].append(sp_o)
            out["pdf"].append(pdf)
        cat = {f: jnp.concatenate(v, axis=1) for f, v in out.items()}  # (M, K, ...)
        K = cat["sp_o"].shape[1]

        def per_pixel(a):
            return a.reshape(P, S * K, *a.shape[2:])

        mat = jnp.broadcast_to(jnp.asarray(self.tobj_mat)[tobj][:, None], (M, K))
        mat = jnp.where(have[:, None], mat, -1)
        return dict(
            mat=per_pixel(mat),
            sp_o=per_pixel(cat["sp_o"]),
            sp_i=per_pixel(cat["sp_i"]),
            cos_i=per_pixel(cat["cos_i"]),
            cos_o=per_pixel(jnp.broadcast_to(cos_o[:, None], (M, K))),
            phase=per_pixel(cat["phase"]),
            pdf=per_pixel(cat["pdf"]),
            weight=per_pixel(cat["weight"]),
        )


def trace(
    scene: Scene, key: PRNGKeyArray | int | None = None, *, progress: bool = False
) -> Transport:
    """The geometric pass over the whole image: `render = shade . trace`.

    **Arguments:** `scene` from `load_scene`; `key` a `jax.random` key or an integer seed
    (default: the scene's `render.seed`).

    **Returns:** a `Transport` for every pixel (its memory grows with the image: for large
    images use `render`, which traces and shades tile by tile).
    """
    from .render import trace_tiles

    return trace_tiles(scene, key, progress=progress)
