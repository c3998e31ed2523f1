"""Light sources as arrays: rectangular (parallelogram) area lights, point lights,
collimated beams and a constant environment.

Radiometry: an area light emits constant radiance `L_e` (W mm^-2 sr^-1) from its front side
(along `edge_u x edge_v`); a point light has intensity `I` (W sr^-1); a beam of radius `R`
carries power `P` (W) along its axis, so a surface inside it receives `P cos / (pi R^2)`.
Irradiance at a point is estimated by stratified (jittered n x n) sampling of each area
light with shadow rays. Beams are not seen by camera rays (a collimated beam has no
radiance in any finite solid angle). An environment light is a constant radiance `L_env`
arriving along every ray that escapes the scene; its irradiance `int L_env V cos dw` is
estimated with cosine-weighted directions (the same stratified samples) and shadow rays.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .scene import AreaLight, BeamLight, EnvironmentLight, PointLight


class LightArrays(eqx.Module):
    """All lights of a scene as stacked arrays (`La` area lights, `Lp` point lights)."""

    corner: Float[Array, "La 3"]
    edge_u: Float[Array, "La 3"]
    edge_v: Float[Array, "La 3"]
    normal: Float[Array, "La 3"]
    area: Float[Array, " La"]
    radiance: Float[Array, "La 3"]
    position: Float[Array, "Lp 3"]
    intensity: Float[Array, "Lp 3"]
    beam_origin: Float[Array, "Lb 3"]
    beam_dir: Float[Array, "Lb 3"]
    beam_radius: Float[Array, " Lb"]
    beam_power: Float[Array, "Lb 3"]
    env_radiance: Float[Array, "Le 3"]

    @classmethod
    def from_scene(cls, lights) -> LightArrays:
        area = [l for l in lights if isinstance(l, AreaLight)]
        point = [l for l in lights if isinstance(l, PointLight)]
        beam = [l for l in lights if isinstance(l, BeamLight)]
        env = [l for l in lights if isinstance(l, EnvironmentLight)]

        def stack(items, attr):
            if not items:
                return jnp.zeros((0, 3))
            return jnp.asarray(np.stack([getattr(x, attr) for x in items]), dtype=float)

        return cls(
            corner=stack(area, "corner"),
            edge_u=stack(area, "edge_u"),
            edge_v=stack(area, "edge_v"),
            normal=stack(area, "normal"),
            area=jnp.asarray([l.area for l in area], dtype=float).reshape(-1),
            radiance=stack(area, "radiance"),
            position=stack(point, "position"),
            intensity=stack(point, "intensity"),
            beam_origin=stack(beam, "position"),
            beam_dir=stack(beam, "direction"),
            beam_radius=jnp.asarray([l.radius for l in beam], dtype=float).reshape(-1),
            beam_power=stack(beam, "power"),
            env_radiance=stack(env, "radiance"),
        )

    def scaled(self, gain: Array, kinds: tuple[str, ...]) -> LightArrays:
        """The lights with each one's emission times `gain` (one factor per light, in the
        scene's order; `kinds` the scene's light types, `"area"`/`"point"`/`"beam"`)."""
        gain = jnp.asarray(gain, dtype=float)

        def of(kind):
            return gain[np.array([i for i, k in enumerate(kinds) if k == kind], dtype=int)]

        return eqx.tree_at(
            lambda la: (la.radiance, la.intensity, la.beam_power, la.env_radiance),
            self,
            (
                self.radiance * of("area")[:, None],
                self.intensity * of("point")[:, None],
                self.beam_power * of("beam")[:, None],
                self.env_radiance * of("environment")[:, None],
            ),
        )

    @property
    def n_area(self) -> int:
        return self.corner.shape[0]

    @property
    def n_point(self) -> int:
        return self.position.shape[0]

    @property
    def n_beam(self) -> int:
        return self.beam_origin.shape[0]

    @property
    def n_env(self) -> int:
        return self.env_radiance.shape[0]

    @property
    def environment(self) -> Float[Array, " 3"]:
        """The environment's radiance (all environment lights together; 0 without one)."""
        return jnp.sum(self.env_radiance, axis=0)

    def beam_frame(self, k: int) -> tuple[Array, Array]:
        """Two unit vectors spanning the cross-section of beam `k`."""
        d = self.beam_dir[k]
        a = jnp.where(jnp.abs(d[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
        e1 = jnp.cross(d, a)
        e1 = e1 / jnp.linalg.norm(e1)
        return e1, jnp.cross(d, e1)

    def intersect(self, o: Array, d: Array, t_max: Array) -> tuple[Array, Array]:
        """Nearest area-light hit before `t_max` along `o + t d`.

        **Returns:** `(t, radiance)`: `t` is inf on a miss; `radiance` is the emitted RGB
        radiance seen along the ray (zero from behind: the lights are one-sided).
        """
        t_best = jnp.full(o.shape[:-1], jnp.inf)
        rad = jnp.zeros(o.shape)
        for k in range(self.n_area):
            c, eu, ev, n = self.corner[k], self.edge_u[k], self.edge_v[k], self.normal[k]
            dn = d @ n
            ok_dn = jnp.abs(dn) > 1e-12
            t = jnp.where(ok_dn, ((c - o) @ n) / jnp.where(ok_dn, dn, 1.0), jnp.inf)
            p = o + t[..., None] * d - c
            # coordinates in the (edge_u, edge_v) basis via the dual basis
            uu, uv, vv = eu @ eu, eu @ ev, ev @ ev
            det = uu * vv - uv * uv
            pu, pv = p @ eu, p @ ev
            a = (vv * pu - uv * pv) / det
            b = (uu * pv - uv * pu) / det
            hit = ok_dn & (t > 1e-4) & (t < jnp.minimum(t_max, t_best))
            hit = hit & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)
            t_best = jnp.where(hit, t, t_best)
            front = (dn < 0)[..., None]
            rad = jnp.where(hit[..., None], jnp.where(front, self.radiance[k], 0.0), rad)
        return t_best, rad


def direct_irradiance(
    lights: LightArrays,
    x: Float[Array, "*b 3"],
    n: Float[Array, "*b 3"],
    u_light: Float[Array, "*b S 2"],
    occluded: Callable[[Array, Array, Array], Array],
    transmit: Callable[[Array], Array] | None = None,
) -> Float[Array, "*b 3"]:
    """Irradiance `E = int L cos dw` at surface points from all lights, with shadows.

    **Arguments:**

    - `x`, `n`: points and unit normals (irradiance on the side `n` points to).
    - `u_light`: `S` stratified samples of the unit square per point (one per area-light
      stratum).
    - `occluded(o, d, t_max) -> bool`: shadow-ray query against the scene's shapes.
    - `transmit(cos)`: optional factor on the cosine (Fresnel transmittance into a medium).

    **Returns:** RGB irradiance, W mm^-2.
    """
    E = jnp.zeros(x.shape)
    S = u_light.shape[-2]
    for k in range(lights.n_area):
        y = (
            lights.corner[k]
            + u_light[..., 0:1] * lights.edge_u[k]
            + u_light[..., 1:2] * lights.edge_v[k]
        )  # (*b, S, 3)
        xo = x[..., None, :]
        w = y - xo
        dist2 = jnp.sum(w * w, axis=-1)
        dist = jnp.sqrt(dist2)
        w = w / dist[..., None]
        cos_x = jnp.sum(w * n[..., None, :], axis=-1)
        cos_l = -(w @ lights.normal[k])
        ok = (cos_x > 0) & (cos_l > 0)
        vis = ~occluded(xo + 1e-3 * n[..., None, :], w, dist * (1 - 1e-4))
        f = transmit(cos_x) if transmit is not None else 1.0
        g = jnp.where(ok & vis, f * cos_x * cos_l / dist2, 0.0)
        E = E + lights.radiance[k] * (lights.area[k] / S) * jnp.sum(g, axis=-1)[..., None]
    for k in range(lights.n_point):
        w = lights.position[k] - x
        dist2 = jnp.sum(w * w, axis=-1)
        dist = jnp.sqrt(dist2)
        w = w / dist[..., None]
        cos_x = jnp.sum(w * n, axis=-1)
        vis = ~occluded(x + 1e-3 * n, w, dist * (1 - 1e-4))
        f = transmit(cos_x) if transmit is not None else 1.0
        g = jnp.where((cos_x > 0) & vis, f * cos_x / dist2, 0.0)
        E = E + lights.intensity[k] * g[..., None]
    if lights.n_env:
        # cosine-weighted directions from the same strata: E = pi L_env mean(V f)
        r = jnp.sqrt(u_light[..., 0])
        phi = 2.0 * jnp.pi * u_light[..., 1]
        t1, t2 = _frame(n)
        w = (
            (r * jnp.cos(phi))[..., None] * t1[..., None, :]
            + (r * jnp.sin(phi))[..., None] * t2[..., None, :]
            + jnp.sqrt(jnp.maximum(1.0 - r * r, 0.0))[..., None] * n[..., None, :]
        )
        cos_x = jnp.sum(w * n[..., None, :], axis=-1)
        xo = jnp.broadcast_to(x[..., None, :], w.shape)
        vis = ~occluded(xo + 1e-3 * n[..., None, :], w, jnp.full(cos_x.shape, jnp.inf))
        f = transmit(cos_x) if transmit is not None else 1.0
        g = jnp.where(vis & (cos_x > 0), f * jnp.ones_like(cos_x), 0.0)
        E = E + jnp.pi * lights.environment * jnp.mean(g, axis=-1)[..., None]
    return E


def _frame(n):
    """Two unit tangents orthogonal to unit normals `n` (Duff et al. 2017)."""
    sign = jnp.where(n[..., 2] >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (sign + n[..., 2])
    b = n[..., 0] * n[..., 1] * a
    t1 = jnp.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], axis=-1)
    t2 = jnp.stack([b, sign + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    return t1, t2


def beam_irradiance(
    lights: LightArrays,
    x: Float[Array, "*b 3"],
    n: Float[Array, "*b 3"],
    occluded: Callable[[Array, Array, Array], Array],
    transmit: Callable[[Array], Array] | None = None,
) -> Float[Array, "*b 3"]:
    """Irradiance `P cos / (pi R^2)` from every beam at points `x` inside it (W mm^-2), with
    a shadow ray back towards the beam's source disc.

    Used for diffuse surfaces. Translucent objects receive beams through the beam points of
    the irradiance cloud instead (`trace`), which resolve a narrow beam exactly.
    """
    E = jnp.zeros(x.shape)
    for k in range(lights.n_beam):
        d = lights.beam_dir[k]
        v = x - lights.beam_origin[k]
        along = v @ d
        radial = jnp.linalg.norm(v - along[..., None] * d, axis=-1)
        inside = (along > 0) & (radial <= lights.beam_radius[k])
        cos_x = -(n @ d)
        vis = ~occluded(x + 1e-3 * n, jnp.broadcast_to(-d, x.shape), along * (1 - 1e-4))
        f = transmit(cos_x) if transmit is not None else 1.0
        g = jnp.where(inside & (cos_x > 0) & vis, f * cos_x, 0.0)
        E = E + lights.beam_power[k] / (jnp.pi * lights.beam_radius[k] ** 2) * g[..., None]
    return E
