"""Single scattering of the diffusion transport: scatter points along the refracted view
ray, each connected to every area and point light through the boundary.

Scatter depths `s'_o` come from a fixed proposal (a truncated exponential at the trace-time
extinction, mixed with uniform, clamped to the object's thickness found by an inside ray
cast) whose exact pdf is stored, so `shade` re-weights `integrand / pdf` for any
coefficients. Each connection records what the medium acts on: Jensen's refracted distance
`s'_i` to the exit point, the cosines and the phase cosine, and the light it carries
(shadow-tested from the exit point). Lengths in mm.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from .._arrays import EPS, SceneArrays
from ..dipole import refracted_distance
from ..sampling import stratified_1d, stratified_2d
from ..scattering import refract
from ._record import NO_RECORD, Recorder

__all__ = ["records_per_sample", "single_scatter", "no_records"]

PROPOSAL_EXP = 0.75  # mixture weight of the exponential in the scatter-depth proposal
FIELDS = ("mat", "sp_o", "sp_i", "cos_i", "cos_o", "phase", "pdf", "weight")


def records_per_sample(arrays: SceneArrays) -> int:
    """Single-scattering records per camera sample (scatter samples x area and point
    lights)."""
    lights = arrays.light_base
    return arrays.sss.single_samples * (lights.n_area + lights.n_point)


def no_records(P: int) -> dict:
    """The records of `P` pixels without single scattering (`K = 0`)."""
    return dict(
        mat=jnp.full((P, 0), -1, jnp.int32),
        **{f: jnp.zeros((P, 0)) for f in ("sp_o", "sp_i", "cos_i", "cos_o", "phase")},
        pdf=jnp.ones((P, 0)),
        weight=jnp.zeros((P, 0, 3)),
    )


def _unit(v):
    n = jnp.linalg.norm(v, axis=-1, keepdims=True)
    return v / jnp.where(n > 0, n, 1.0)


def _light_targets(arrays: SceneArrays, key: PRNGKeyArray, M: int, n_ss: int):
    """One stratified point per scatter sample on each area light, and each point light:
    `[(y (M, n_ss, 3), k, kind)]`."""
    lights = arrays.lights
    targets = []
    for k in range(lights.n_area):
        ul = stratified_2d(jax.random.fold_in(key, k), n_ss, (M,))
        y = lights.corner[k] + ul[..., 0:1] * lights.edge_u[k] + ul[..., 1:2] * lights.edge_v[k]
        targets.append((y, k, "area"))
    for k in range(lights.n_point):
        targets.append((jnp.broadcast_to(lights.position[k], (M, n_ss, 3)), k, "point"))
    return targets


def single_scatter(
    arrays: SceneArrays, key: PRNGKeyArray, s: dict, P: int, S: int, rec: Recorder = NO_RECORD
) -> dict:
    """The single-scattering records of the samples `s` (the chains' slots flattened to
    `M = P S` rows): `FIELDS` -> `(P, K, ...)` with `K = spp x records_per_sample`."""
    M = P * S
    n_ss = arrays.sss.single_samples
    have, xo, din, tobj, T_slot = s["have"], s["xo"], s["din"], s["tobj"], s["T_slot"]
    k1, k2, k3, _ = jax.random.split(key, 4)
    eta = arrays.object_eta()[tobj][:, None]  # (M, 1)
    lam = arrays.object_sigma_t()[tobj][:, None]
    # thickness along the refracted ray
    thick, _ = arrays.intersect_object(tobj, xo - EPS * 0.5 * din, din)
    thick = jnp.where(have & jnp.isfinite(thick), thick, 0.0)[:, None]  # (M,1)
    ok_thick = thick > 0
    th = jnp.where(ok_thick, thick, 1.0)
    # proposal: truncated exponential (rate lam) on [0, th] mixed with uniform
    u_sel = stratified_1d(k1, n_ss, (M,))
    u_s = jax.random.uniform(k2, (M, n_ss))
    use_exp = u_sel < PROPOSAL_EXP
    norm = -jnp.expm1(-lam * th)
    s_exp = -jnp.log1p(-u_s * norm) / lam
    sp_o = jnp.where(use_exp, s_exp, u_s * th)
    pdf = PROPOSAL_EXP * lam * jnp.exp(-lam * sp_o) / norm + (1 - PROPOSAL_EXP) / th
    xs = xo[:, None, :] + sp_o[..., None] * din[:, None, :]  # (M, n_ss, 3)
    rec.ss_paths(xo, xs, have)
    lights = arrays.lights
    out = {f: [] for f in ("sp_i", "cos_i", "phase", "weight", "sp_o", "pdf")}
    for y, k, kind in _light_targets(arrays, k3, M, n_ss):
        w = _unit(y - xs)
        t_exit, n_i = arrays.intersect_object(jnp.broadcast_to(tobj[:, None], (M, n_ss)), xs, w)
        found = jnp.isfinite(t_exit)
        t_e = jnp.where(found, t_exit, 0.0)
        xi = xs + t_e[..., None] * w
        cos_i = jnp.sum(w * n_i, axis=-1)
        dist = jnp.linalg.norm(y - xi, axis=-1)
        rec.ss_exit(xs, xi)
        vis = ~arrays.occluded(xi + EPS * n_i, w, dist * (1 - 1e-4), rec)
        prop_in, ok_r = refract(-w, n_i, eta[..., None])
        if kind == "area":
            cos_l = jnp.maximum(-(w @ lights.normal[k]), 0.0)
            Lg = lights.radiance[k] * (lights.area[k] * cos_l / dist**2)[..., None]
        else:
            Lg = lights.intensity[k] * (1.0 / dist**2)[..., None]
        valid = have[:, None] & ok_thick & found & (cos_i > 0) & vis & ok_r
        out["sp_i"].append(refracted_distance(t_e, cos_i, eta))
        out["cos_i"].append(cos_i)
        out["phase"].append(jnp.sum(prop_in * -din[:, None, :], axis=-1))
        out["weight"].append(jnp.where(valid[..., None], T_slot[:, None, :] * Lg, 0.0) / (n_ss * S))
        out["sp_o"].append(sp_o)
        out["pdf"].append(pdf)
    cat = {f: jnp.concatenate(v, axis=1) for f, v in out.items()}  # (M, K, ...)
    K = cat["sp_o"].shape[1]
    mat = jnp.broadcast_to(jnp.asarray(arrays.tobj_mat, dtype=jnp.int32)[tobj][:, None], (M, K))
    cat["mat"] = jnp.where(have[:, None], mat, -1)
    cat["cos_o"] = jnp.broadcast_to(s["cos_o"][:, None], (M, K))
    return {f: cat[f].reshape(P, S * K, *cat[f].shape[2:]) for f in FIELDS}
