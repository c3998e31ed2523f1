"""The dipole gather of the diffusion transport: per pixel, the weights of the diffusion
profile `R_d(r)` on fixed distance nodes.

`R_d` depends on geometry only through `r = |x_o - x_i|`, so `F_t(cos_o)/pi sum_i R_d(r_oi)
E_i A_i` is stored per pixel as weights on `B` fixed nodes (linear "hat" interpolation in
`log(1 + r / R0_MM)`): `shade` is then a small matrix product, independent of the number of
source points. The sources are the irradiance cloud (each of a pixel's `spp` samples
gathers a stratified `1/spp` subset, scaled by `spp`, plus an exact flat-disc near field),
the beam points, or per-pixel Monte Carlo samples (the `uniform`, `within` and `annulus`
strategies, `sssjax.transport.STRATEGIES`). Lengths in mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from .._arrays import SceneArrays
from ..lights import direct_irradiance
from ..sampling import stratified_1d, stratified_2d
from ..scattering import fresnel_transmittance
from ._record import NO_RECORD, Recorder
from ._strategies import Strategy
from .cloud import Cloud

__all__ = [
    "R0_MM",
    "Nodes",
    "disc_node_weights",
    "gather_cloud",
    "gather_beams",
    "gather_samples",
]

R0_MM = 0.1  # mm: scale of the log distance nodes


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


@dataclass(frozen=True, eq=False)
class Nodes:
    """The distance nodes of a scene: `r_nodes` (`B`, mm) from 0 to just past the largest
    translucent object's diagonal, their spacing `du` in `log(1 + r / R0_MM)`, and per object
    the near-field radius `r_near` (two cloud spacings) with its disc weights `near_weights`
    (`No x B`)."""

    r_nodes: np.ndarray
    du: float
    r_near: tuple
    near_weights: np.ndarray

    @classmethod
    def of(cls, arrays: SceneArrays, cloud_n: int) -> Nodes:
        bins = arrays.sss.bins
        r_max = 1.01 * arrays.tobj_diag
        du = math.log1p(r_max / R0_MM) / (bins - 1)
        r_nodes = R0_MM * np.expm1(np.arange(bins) * du)
        r_near = tuple(2.0 * math.sqrt(a / cloud_n) for a in arrays.tobj_area)
        near = np.stack(
            [disc_node_weights(r_nodes, R0_MM, du, R) for R in r_near] or [np.zeros(bins)]
        )
        return cls(r_nodes, du, r_near, near)

    @property
    def bins(self) -> int:
        return len(self.r_nodes)

    def bin(self, arrays: SceneArrays, r, w, tobj, P, S):
        """Scatter weights `w (M, n, 3)` at distances `r (M, n)` onto the nodes of each
        sample's pixel and material (linear hat interpolation in `log(1 + r / r0)`).

        **Returns:** `(Mt, P, B, 3)`.
        """
        Mt, B = len(arrays.materials), self.bins
        u = jnp.log1p(r / R0_MM) / self.du
        b0 = jnp.clip(jnp.floor(u), 0, B - 2).astype(jnp.int32)
        frac = jnp.clip(u - b0, 0.0, 1.0)[..., None]
        pix = jnp.repeat(jnp.arange(P), S)[:, None]
        mat = jnp.asarray(arrays.tobj_mat, dtype=jnp.int32)[tobj][:, None]
        flat = (mat * P + pix) * B + b0
        hist = jnp.zeros((Mt * P * B, 3), w.dtype)
        hist = hist.at[flat.ravel()].add((w * (1 - frac)).reshape(-1, 3))
        hist = hist.at[(flat + 1).ravel()].add((w * frac).reshape(-1, 3))
        return hist.reshape(Mt, P, B, 3)


def _exit_factor(arrays: SceneArrays, s: dict):
    """`T F_t(cos_o) / pi` per sample `(M, 3)` (zero where `have` is False), and `F_t`."""
    eta = arrays.object_eta()[s["tobj"]]
    Ft_o = fresnel_transmittance(s["cos_o"], eta)
    w_o = jnp.where(s["have"], 1.0, 0.0)[:, None] * s["T_slot"] * (Ft_o / jnp.pi)[:, None]
    return w_o, Ft_o


def _subsets(points, values, s: dict, P, S):
    """Each sample's `1/spp` subset of per-object source points (`points`, `values`:
    `(No, N, 3)`): sample `s` of a pixel takes points `s, s + S, s + 2S, ...` of its
    object. **Returns:** `p (P, S, n, 3)`, distances `r (M, n)` and `values (M, n, 3)`."""
    M = P * S
    n_sub = points.shape[1] // S
    # broadcasting over pixels and selecting the object with `where` avoids a gather
    # indexed by data (which XLA on CPU does slowly)
    pts = points.reshape(-1, n_sub, S, 3).transpose(0, 2, 1, 3)
    val = values.reshape(-1, n_sub, S, 3).transpose(0, 2, 1, 3)
    tob = s["tobj"].reshape(P, S, 1, 1)
    p, v = pts[0][None], val[0][None]
    for jo in range(1, pts.shape[0]):
        p = jnp.where(tob == jo, pts[jo][None], p)
        v = jnp.where(tob == jo, val[jo][None], v)
    r = jnp.linalg.norm(p - s["xo"].reshape(P, S, 1, 3), axis=-1).reshape(M, n_sub)
    v = jnp.broadcast_to(v, (P, S, n_sub, 3)).reshape(M, n_sub, 3)
    return p, r, v


def gather_cloud(
    arrays: SceneArrays, nodes: Nodes, cloud: Cloud, s: dict, P, S, rec: Recorder = NO_RECORD
):
    """Node weights of `F_t(cos_o)/pi int R_d(|x_o - x|) E(x) dA(x)` for the samples `s`
    (the chains' slots, flattened to `M = P S` rows): `(Mt, P, B, 3)`.

    Far field (`r >= R_near`): the cloud sum `sum_i R_d(r_oi) E_i A_i`. Near field: the
    surface is taken as a flat disc of radius `R_near` lit by `E(x_o)`, integrated exactly
    on the nodes (`near_weights`). This removes the blotches a point cloud leaves where
    `R_d` is steepest, at the cost of assuming flatness within `R_near` (about two cloud
    spacings).
    """
    Mt, B = len(arrays.materials), nodes.bins
    have, tobj = s["have"], s["tobj"]
    p, r, E = _subsets(cloud.points, cloud.irradiance, s, P, S)
    w_o, Ft_o = _exit_factor(arrays, s)
    # spp subsets of 1/spp of the cloud each: scale by spp, then average over spp -> 1
    w_o = w_o * cloud.area[tobj][:, None] / S  # area per point; / S for the pixel mean
    far = (r >= jnp.asarray(nodes.r_near, dtype=float)[tobj][:, None])[..., None]
    w = jnp.where(far, w_o[:, None, :] * E * S, 0.0)  # (M, n_sub, 3)
    rec.points(p, w, have)
    hist = nodes.bin(arrays, r, w, tobj, P, S)
    mat = jnp.asarray(arrays.tobj_mat, dtype=jnp.int32)[tobj][:, None]
    # near field: (T F_t / pi) E(x_o) int_{r < R_near} 2 pi r R_d(r) dr, on the nodes
    w_near = jnp.where(have[:, None], s["T_slot"] * s["E_o"] * (Ft_o / jnp.pi)[:, None], 0.0)
    w_near = w_near / S
    nw = jnp.asarray(nodes.near_weights, dtype=float)[tobj]  # (M, B)
    onehot = (mat == jnp.arange(Mt)).astype(w_near.dtype)  # (M, Mt)
    near = jnp.einsum(
        "psb,psc,psm->mpbc",
        nw.reshape(P, S, B),
        w_near.reshape(P, S, 3),
        onehot.reshape(P, S, Mt),
    )
    return hist + near


def gather_beams(
    arrays: SceneArrays, nodes: Nodes, cloud: Cloud, s: dict, P, S, rec: Recorder = NO_RECORD
):
    """Node weights of `F_t(cos_o)/pi sum_i R_d(|x_o - x_i|) Phi_i` over the beam rays
    (power `Phi_i` entering at `x_i`), each sample gathering a stratified `1/spp` subset
    (scaled by spp). No near-field disc: the beam points are the source."""
    p, r, Phi = _subsets(cloud.beam_points, cloud.beam_flux, s, P, S)
    w_o, _ = _exit_factor(arrays, s)
    w = w_o[:, None, :] * Phi  # (M, n_sub, 3): x S for the subset, / S for the mean
    rec.points(p, w, s["have"])
    return nodes.bin(arrays, r, w, s["tobj"], P, S)


def gather_samples(
    arrays: SceneArrays,
    nodes: Nodes,
    strategy: Strategy,
    key: PRNGKeyArray,
    s: dict,
    P,
    S,
    rec: Recorder = NO_RECORD,
):
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
    cfg = arrays.sss
    M = P * S
    K = cfg.samples
    T = strategy.tries(cfg)
    nl = arrays.render.light_samples
    have, xo, tobj = s["have"], s["xo"], s["tobj"]
    k1, k2, k3 = jax.random.split(key, 3)
    u2 = stratified_2d(k1, K * T, (M,))  # stratified over the slots x tries of a sample
    u1 = stratified_1d(k2, K * T, (M,))
    u = jnp.concatenate([u2, u1[..., None]], axis=-1).reshape(M, K, T, 3)
    p = jnp.zeros((M, K, T, 3))
    n = jnp.zeros((M, K, T, 3))
    area = jnp.zeros(M)
    eta = jnp.ones(M)
    for j, i in enumerate(arrays.tobj_shape):
        pj, nj = arrays.shapes[i].sample(u)
        sel = (tobj == j)[:, None, None, None]
        p = jnp.where(sel, pj, p)
        n = jnp.where(sel, nj, n)
        area = jnp.where(tobj == j, arrays.tobj_area[j], area)
        eta = jnp.where(tobj == j, arrays.eta[i], eta)
    r = jnp.linalg.norm(p - xo[:, None, None, :], axis=-1)  # (M, K, T)
    acc = strategy.region(r, cfg)
    n_acc = jnp.sum(acc, axis=-1)  # (M, K)
    first = jnp.argmax(acc, axis=-1)
    take = lambda a: jnp.take_along_axis(a, first[..., None, None], axis=2)[:, :, 0]  # noqa: E731
    p1, n1 = take(p), take(n)
    r1 = jnp.take_along_axis(r, first[..., None], axis=2)[..., 0]
    ul = stratified_2d(k3, nl * nl, (M, K))
    rec.dipole(xo, p1, have)

    def transmit(c):
        return fresnel_transmittance(c, eta.reshape((-1,) + (1,) * (c.ndim - 1)))

    def occluded(o_, d_, t_max):
        return arrays.occluded(o_, d_, t_max, rec)

    E = direct_irradiance(arrays.lights, p1, n1, ul, occluded, transmit)  # (M, K, 3)
    w_o, _ = _exit_factor(arrays, s)
    scale = area[:, None] * n_acc / (T * K * S)  # (M, K)
    w = w_o[:, None, :] * E * scale[..., None]
    rec.points(p1, w, have)
    return nodes.bin(arrays, r1, w, tobj, P, S)
