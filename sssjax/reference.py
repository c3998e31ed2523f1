"""Monte Carlo ground truth: a volumetric random walk under a pencil beam.

The classic dipole (`sssjax.dipole`) and the better profiles are *approximations* to
radiative transfer. This module solves the transport problem they approximate, by brute
force, so that their error can be measured:

- **Geometry.** A semi-infinite homogeneous medium `z < 0` below a flat, smooth dielectric
  surface `z = 0`; `eta` is the relative index (inside / outside).
- **Source.** A pencil beam of unit power hitting the surface at the origin from above, at
  `theta_i` degrees from the normal (in the x-z plane). The first-surface (specular) Fresnel
  reflection `F(cos theta_i, eta)` is computed exactly (it is not sampled); the rest enters
  along the refracted direction.
- **Transport.** Exact exponential free flights with `sigma_t = sigma_a + sigma_s`,
  Henyey-Greenstein scattering with mean cosine `g`.
- **Absorption by weight** (implicit capture): a photon never dies at a collision, its
  weight is multiplied by the single-scattering albedo `sigma_s / sigma_t` and the
  remainder is booked as absorbed. A photon whose weight drops below `w_min` (by default
  `0.25 albedo^2`: after two collisions' worth of absorption) plays **Russian roulette**:
  it survives with probability `w / w_survive` (`w_survive = 2 w_min`) and then carries
  weight `w_survive`, otherwise it dies. This is unbiased (the expected weight is
  unchanged); the weight it creates or destroys is booked as `roulette` (expectation 0),
  so the bookkeeping closes photon by photon:
  `specular + diffuse + absorbed + lost + roulette = 1` up to float rounding.
- **Boundary.** Every time a photon reaches the surface from inside, its weight is *split*
  with the exact unpolarised Fresnel reflectance `F(mu, 1/eta)` (`mu` the cosine with the
  normal; total internal reflection gives `F = 1`): `w (1 - F)` leaves and is scored at
  that point, `w F` is mirrored back into the medium (its next free flight is drawn anew:
  free flights are memoryless). Splitting instead of choosing is unbiased and scores every
  surface hit, which lowers the variance of the profile.
- **Far photons.** A photon farther than `r_cap` (3D distance from the entry point) or older
  than `max_steps` free flights is stopped and its weight booked as `lost`: it is neither
  reflected nor absorbed as far as the tallies know. With absorption it is negligible
  (its weight has decayed); in a non-absorbing medium it is the light that would still
  come out, far away and late.
- **Single scattering.** Light leaving after exactly one scattering event (collision) is
  tallied separately, as a profile and a total. The diffusion profiles model *multiple*
  scattering only: compare them with `profile - single_profile` (`multiple_profile`).

**Normalisation.** Every tally in a `Reference` is **per unit incident power** (entry Fresnel
loss included): `diffuse` is the fraction of the beam's power that comes back out after
entering, and `profile` is the exitant radiant exitance in mm^-2 per unit incident power,
azimuthally averaged, as a function of the distance `r` from the entry point.
`Reference.entered()` rescales every tally by `1 / (1 - specular)`, i.e. to per unit power
that **entered** the medium: that is the normalisation of `sssjax.dipole.Rd` and
`Rd_total`.

**Statistics.** Photons are traced in a pool of `pool` slots (refilled as photons finish),
assigned round-robin to `n_batches` independent batches; standard errors are those of the
batch means (ratio estimator over batch photon counts), so they include every source of
variance (splitting, roulette).

**Arithmetic.** The walk runs in the default JAX float (float32 unless x64 is on); tallies
are accumulated per call in that float and across calls in float64.

The walk is one `jit`-compiled `jax.lax.fori_loop` over free flights of the whole pool, with
explicit `jax.random` keys (`fold_in` of the seed and the step index): the same arguments
and seed give the same result on the same machine.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ._numerics import float_dtype
from .dipole import fresnel_reflectance
from .media import Medium

__all__ = [
    "Reference",
    "simulate",
    "simulate_medium",
    "merge",
    "to_profile",
    "default_edges",
    "single_scatter_total",
    "single_scatter_profile",
    "single_scatter_exitance",
]

# columns of the per-batch tally: the weight leaving, the number of exit events, and the
# per-batch scalars (which do not depend on the bin column they are scattered to)
_W, _N, _ABS, _LOST, _RR, _LAUNCH, _STEPS = range(7)
_NQ = 7


# --- the result ----------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Reference:
    """The Monte Carlo answer for one set of coefficients (one colour channel).

    All tallies are per unit **incident** power unless `normalization == "entered"` (see
    `entered()`); profiles are in mm^-2 (radiant exitance per unit power), totals are
    dimensionless fractions. Each `*_stderr` is one standard error of the estimate above it.

    **Fields:**

    - `sigma_a`, `sigma_s` (mm^-1), `g`, `eta`, `theta_i` (degrees): the inputs.
    - `n_photons`, `n_batches`: photons traced and the batches used for the errors.
    - `r_edges` `(n + 1,)` mm: the radial bins (the first is `[0, r_edges[1]]`, the others
      logarithmic by default); `r` `(n,)`: the area-weighted mean radius of each bin.
    - `profile`: exitance of all light leaving after entering (single + multiple).
    - `single_profile`: the part that scattered exactly once; `multiple_profile`: the rest.
    - `counts`: the number of exit events scored in each bin (all orders).
    - `specular`: the first-surface Fresnel reflection `F(cos theta_i, eta)` (exact).
    - `diffuse`: total light leaving after entering, at any `r` (including `beyond`).
    - `single`, `multiple`: its single- and multiple-scattering parts.
    - `beyond`: the part of `diffuse` that left at `r >= r_edges[-1]` (outside the profile).
    - `absorbed`: absorbed in the medium; `lost`: stopped far away (see the module notes).
    - `roulette`: net weight destroyed by Russian roulette (expectation 0).
    - `steps_per_photon`: mean number of free flights (collisions + surface hits) per photon.
    - `seconds`: wall time of the walk (compilation included on a first call).
    - `normalization`: `"incident"` or `"entered"`.
    """

    sigma_a: float
    sigma_s: float
    g: float
    eta: float
    theta_i: float
    n_photons: int
    n_batches: int
    r_edges: np.ndarray
    r: np.ndarray
    profile: np.ndarray
    profile_stderr: np.ndarray
    single_profile: np.ndarray
    single_profile_stderr: np.ndarray
    multiple_profile: np.ndarray
    multiple_profile_stderr: np.ndarray
    counts: np.ndarray
    specular: float
    diffuse: float
    diffuse_stderr: float
    single: float
    single_stderr: float
    multiple: float
    multiple_stderr: float
    beyond: float
    beyond_stderr: float
    absorbed: float
    absorbed_stderr: float
    lost: float
    lost_stderr: float
    roulette: float
    roulette_stderr: float
    steps_per_photon: float
    seconds: float
    normalization: str = "incident"

    @property
    def transmitted(self) -> float:
        """`1 - specular`: the fraction of the incident power that enters the medium."""
        return 1.0 - self.specular

    @property
    def sigmap_t(self) -> float:
        """Reduced extinction `sigma_a + sigma_s (1 - g)`, mm^-1 (one over the reduced mfp)."""
        return self.sigma_a + self.sigma_s * (1.0 - self.g)

    @property
    def balance(self) -> float:
        """`specular + diffuse + absorbed + lost + roulette` per unit incident power:
        1 up to float rounding (the bookkeeping closes photon by photon)."""
        s = 1.0 if self.normalization == "incident" else self.transmitted
        return self.specular + s * (self.diffuse + self.absorbed + self.lost + self.roulette)

    def entered(self) -> Reference:
        """The same result per unit power that **entered** the medium (every tally divided
        by `1 - specular`; `specular` itself is left as it is). This is the normalisation of
        `sssjax.dipole.Rd` / `Rd_total`."""
        if self.normalization == "entered":
            return self
        t = self.transmitted
        if t <= 0:
            raise ValueError("Reference.entered: no power entered the medium (specular = 1)")
        scaled = {
            f.name: getattr(self, f.name) / t
            for f in dataclasses.fields(self)
            if f.name in _TALLIES
        }
        return dataclasses.replace(self, normalization="entered", **scaled)

    def summary(self) -> str:
        """A few lines with the totals and their standard errors."""
        return (
            f"sigma_a={self.sigma_a:g} sigma_s={self.sigma_s:g} g={self.g:g} eta={self.eta:g} "
            f"theta_i={self.theta_i:g}: {self.n_photons} photons, "
            f"{self.steps_per_photon:.1f} steps/photon, {self.seconds:.2f} s "
            f"(per unit {self.normalization} power)\n"
            f"  specular {self.specular:.6f}\n"
            f"  diffuse  {self.diffuse:.6f} +- {self.diffuse_stderr:.6f} "
            f"(single {self.single:.6f} +- {self.single_stderr:.6f}, "
            f"beyond the bins {self.beyond:.2e})\n"
            f"  absorbed {self.absorbed:.6f} +- {self.absorbed_stderr:.6f}\n"
            f"  lost     {self.lost:.2e} +- {self.lost_stderr:.1e}, "
            f"roulette {self.roulette:+.2e} +- {self.roulette_stderr:.1e}"
        )


_TALLIES = {
    "profile",
    "profile_stderr",
    "single_profile",
    "single_profile_stderr",
    "multiple_profile",
    "multiple_profile_stderr",
    "diffuse",
    "diffuse_stderr",
    "single",
    "single_stderr",
    "multiple",
    "multiple_stderr",
    "beyond",
    "beyond_stderr",
    "absorbed",
    "absorbed_stderr",
    "lost",
    "lost_stderr",
    "roulette",
    "roulette_stderr",
}


# --- the walk ------------------------------------------------------------------------------
def default_edges(sigmap_t: float, n_per_decade: int = 10) -> np.ndarray:
    """Radial bin edges (mm): `[0]` then logarithmic from 0.01 to 100 reduced mean free
    paths `1 / sigmap_t`, `n_per_decade` bins per decade."""
    ell = 1.0 / sigmap_t
    return np.concatenate([[0.0], ell * np.logspace(-2, 2, 4 * n_per_decade + 1)])


def _empty_state(pool: int, n_batches: int, dtype):
    z = jnp.zeros((pool,), dtype)
    zi = jnp.zeros((pool,), jnp.int32)
    batch = jnp.arange(pool, dtype=jnp.int32) % n_batches
    return (z, z, z, z, z, z, z, zi, zi, batch, jnp.zeros((pool,), bool))


def _hg_cos(u, g):
    """Sample the cosine of the Henyey-Greenstein scattering angle from `u` in [0, 1)."""
    small = jnp.abs(g) < 1e-3
    gs = jnp.where(small, 0.5, g)
    frac = (1.0 - gs * gs) / (1.0 - gs + 2.0 * gs * u)
    cos_hg = (1.0 + gs * gs - frac * frac) / (2.0 * gs)
    return jnp.clip(jnp.where(small, 2.0 * u - 1.0, cos_hg), -1.0, 1.0)


def _rotate(dx, dy, dz, cos_t, phi):
    """The direction at polar angle `acos(cos_t)`, azimuth `phi` around `(dx, dy, dz)`
    (branchless orthonormal basis of Duff et al. 2017)."""
    sign = jnp.where(dz >= 0, 1.0, -1.0).astype(dz.dtype)
    a = -1.0 / (sign + dz)
    b = dx * dy * a
    t = (1.0 + sign * dx * dx * a, sign * b, -sign * dx)
    s = (b, sign + dy * dy * a, -dy)
    sin_t = jnp.sqrt(jnp.maximum(1.0 - cos_t * cos_t, 0.0))
    cp, sp = sin_t * jnp.cos(phi), sin_t * jnp.sin(phi)
    nx = cp * t[0] + sp * s[0] + cos_t * dx
    ny = cp * t[1] + sp * s[1] + cos_t * dy
    nz = cp * t[2] + sp * s[2] + cos_t * dz
    inv = jax.lax.rsqrt(nx * nx + ny * ny + nz * nz)  # keep unit length in float32
    return nx * inv, ny * inv, nz * inv


# Always compiled with LLVM's full optimisation, whatever XLA_FLAGS says (the test suite
# lowers it to 0 to compile its many small programs faster): the walk is one small program
# run for minutes, 5-7x slower at level 0 (measured: 32k photons 30 s against 4.5 s).
@functools.partial(
    jax.jit,
    static_argnames=("n_iter", "n_cols", "n_batches", "split", "log_bins"),
    compiler_options={"xla_backend_optimization_level": 3},
)
def _advance(
    state, launched, key, it0, n_total, params, edges, *, n_iter, n_cols, n_batches, split, log_bins
):
    """`n_iter` free flights of the whole pool; returns the new state, the launch counter
    and the tally `(n_batches * n_cols, K, 7)` of this call, one slice per albedo of
    `log_ratios` (K,): the walk's weights times `(albedo_k / albedo)^n` after `n`
    collisions (perturbation Monte Carlo; `log_ratios = [0]` is the walk itself)."""
    sigma_t, albedo, g, inv_eta, d0x, d0z, r_cap2, max_steps, w_min, w_surv, log_ratios = params
    n_k = log_ratios.shape[0]
    n_bins = edges.shape[0] - 1
    pool = state[0].shape[0]
    dtype = state[0].dtype

    def body(i, carry):
        st, launched, tab = carry
        x, y, z, dx, dy, dz, w, nscat, steps, batch, active = st
        u = jax.random.uniform(jax.random.fold_in(key, it0 + i), (4, pool), dtype)

        # refill free slots with new photons, entering at the origin
        free = ~active
        new = jax.lax.cond(
            launched + pool <= n_total,
            lambda: free,  # room for every free slot: no need to rank them
            lambda: free & (launched + jnp.cumsum(free.astype(jnp.int32)) - 1 < n_total),
        )
        launched = launched + jnp.sum(new, dtype=jnp.int32)
        zero = jnp.zeros_like(x)
        x, y, z = jnp.where(new, zero, x), jnp.where(new, zero, y), jnp.where(new, zero, z)
        dx = jnp.where(new, d0x, dx)
        dy = jnp.where(new, zero, dy)
        dz = jnp.where(new, d0z, dz)
        w = jnp.where(new, 1.0, w)
        nscat = jnp.where(new, 0, nscat)
        steps = jnp.where(new, 0, steps)
        active = active | new

        # free flight, or the surface if it comes first
        s = -jnp.log1p(-u[0]) / sigma_t
        up = dz > 0
        t_surf = jnp.where(up, -z / jnp.where(up, dz, 1.0), jnp.inf)
        hit = active & (s >= t_surf)
        coll = active & ~hit
        step = jnp.where(hit, t_surf, s)
        x, y = x + step * dx, y + step * dy
        z = jnp.where(hit, 0.0, jnp.minimum(z + step * dz, 0.0))

        # at the surface: split the weight with the exact Fresnel reflectance
        F = fresnel_reflectance(dz, inv_eta)
        if split:
            w_exit = jnp.where(hit, w * (1.0 - F), 0.0)
            gone = jnp.zeros_like(hit)
        else:  # analog: leave with probability 1 - F (u[1] is free: no collision here)
            gone = hit & (u[1] >= F)
            w_exit = jnp.where(gone, w, 0.0)
        r = jnp.sqrt(x * x + y * y)
        if log_bins:  # edges[1:] geometric: the bin in closed form
            r1, inv_log_ratio = edges[1], 1.0 / jnp.log(edges[2] / edges[1])
            k = jnp.floor(jnp.log(jnp.maximum(r, r1) / r1) * inv_log_ratio)
            col = jnp.where(r < r1, 0, 1 + jnp.minimum(k, n_bins).astype(jnp.int32))
        else:
            col = jnp.searchsorted(edges, r, side="right", method="scan") - 1
        col = jnp.clip(col, 0)
        col = jnp.minimum(col, n_bins)  # n_bins: beyond the last edge
        col = col + jnp.where(nscat == 1, n_bins + 1, 0)  # single scattering block
        w = jnp.where(hit, w * F, w) if split else jnp.where(gone, 0.0, w)
        dz = jnp.where(hit, -dz, dz)

        # at a collision: implicit capture, then a Henyey-Greenstein direction
        f_old = jnp.exp(nscat.astype(dtype)[:, None] * log_ratios)  # (pool, K)
        w_abs = jnp.where(coll, w, 0.0)[:, None] * f_old * (1.0 - albedo * jnp.exp(log_ratios))
        w = jnp.where(coll, w * albedo, w)
        nscat = nscat + coll.astype(jnp.int32)
        f_new = jnp.exp(nscat.astype(dtype)[:, None] * log_ratios)
        ndx, ndy, ndz = _rotate(dx, dy, dz, _hg_cos(u[1], g), 2.0 * jnp.pi * u[2])
        dx, dy, dz = jnp.where(coll, ndx, dx), jnp.where(coll, ndy, dy), jnp.where(coll, ndz, dz)

        # stop far-away and old photons; Russian roulette for light ones
        steps = steps + active.astype(jnp.int32)
        far = active & ((x * x + y * y + z * z > r_cap2) | (steps >= max_steps))
        w_lost = jnp.where(far, w, 0.0)
        low = active & ~far & (w < w_min)
        survive = u[3] * w_surv < w
        w_rr = jnp.where(low, jnp.where(survive, w - w_surv, w), 0.0)
        w = jnp.where(low, jnp.where(survive, w_surv, 0.0), w)
        was_active = active
        active = active & ~gone & ~far & ~(low & ~survive)

        def each(v):
            return jnp.broadcast_to(v.astype(dtype)[:, None], (pool, n_k))

        upd = jnp.stack(
            [
                w_exit[:, None] * f_old,
                each(hit),
                w_abs,
                w_lost[:, None] * f_new,
                w_rr[:, None] * f_new,
                each(new),
                each(was_active),
            ],
            axis=2,
        )
        tab = tab.at[batch * n_cols + col].add(upd, mode="promise_in_bounds")
        st = (x, y, z, dx, dy, dz, w, nscat, steps, batch, active)
        return st, launched, tab

    tab = jnp.zeros((n_batches * n_cols, n_k, _NQ), dtype)
    return jax.lax.fori_loop(0, n_iter, body, (state, launched, tab))


def _compact(state, keep_pool):
    """Move the active photons into a smaller pool (host side; keeps their batch)."""
    arrs = [np.asarray(a) for a in state]
    idx = np.flatnonzero(arrs[-1])
    out = []
    for a in arrs:
        b = np.zeros((keep_pool,), a.dtype)
        b[: idx.size] = a[idx]
        out.append(b)
    return tuple(jnp.asarray(b) for b in out)


def _check(name, value, ok, what):
    if not ok:
        raise ValueError(f"reference.simulate: {name} must be {what}, got {value!r}")


# `simulate` is long for its signature and documented arguments (about 55 lines); its body,
# checks then the batched walk loop, reads best in one piece.
def simulate(
    sigma_a: float,
    sigma_s: float,
    g: float = 0.0,
    eta: float = 1.3,
    *,
    theta_i: float = 0.0,
    n_photons: int = 1_000_000,
    seed: int = 0,
    r_edges: ArrayLike | None = None,
    r_cap: float | None = None,
    max_steps: int = 100_000,
    pool: int = 8192,
    n_batches: int = 64,
    n_iter: int = 256,
    w_min: float | None = None,
    w_survive: float | None = None,
    split: bool = True,
    albedos: ArrayLike | None = None,
    progress: Callable[[int, int], None] | bool = False,
) -> Reference | tuple[Reference, ...]:
    """Trace `n_photons` photons of a pencil beam into a semi-infinite medium.

    **Arguments:**

    - `sigma_a`, `sigma_s`: absorption and scattering coefficients, mm^-1 (scalars; one
      colour channel; `sigma_a + sigma_s > 0`).
    - `g`: Henyey-Greenstein mean cosine, `|g| < 1`.
    - `eta`: relative index of refraction of the medium (inside / outside), `> 0`.
    - `theta_i`: angle of incidence of the beam in degrees, `0 <= theta_i < 90`.
    - `n_photons`: photons to trace (at least `n_batches`).
    - `seed`: the `jax.random` seed.
    - `r_edges`: radial bin edges in mm, increasing, starting at 0 (default:
      `default_edges(sigmap_t)`, 0.01 to 100 reduced mean free paths, 10 bins per decade).
    - `r_cap`: photons farther than this (3D, mm) from the entry point are stopped and booked
      as `lost` (default: 10 times the last edge).
    - `max_steps`: photons older than this many free flights are stopped (`lost`).
    - `pool`, `n_batches`, `n_iter`: photons traced at once, batches for the standard errors
      (`pool` is rounded up to a multiple), and free flights per compiled call.
    - `w_min`, `w_survive`: the Russian roulette threshold and survivor weight (default
      `0.25 albedo^2`, at least 1e-6, and `2 w_min`; chosen for the best variance per unit
      time from marble to ketchup's blue channel, whose multiple scattering a fixed
      threshold would leave to a few lucky survivors).
    - `split`: split the weight at the surface with the Fresnel reflectance (default); with
      `False` a photon leaves whole with probability `1 - F` (analog), which is also unbiased.
    - `albedos`: re-weight the same walk to these single-scattering albedos (each in
      `(0, sigma_s / sigma_t]`, at the same `sigma_t`): a photon's weight after `n`
      collisions is multiplied by `(albedo_k / albedo)^n` (perturbation Monte Carlo), which
      is unbiased for each, with the variance of its own walk or less. One walk of the
      brightest medium thus serves a whole range of bright ones (`benchmarks/profile_table.py`).
    - `progress`: `True` to print progress, or a callable `(done, n_photons)`.

    **Returns:** a `Reference` (per unit incident power; `.entered()` for per unit entered
    power), or with `albedos` a tuple of them, one per albedo (their `sigma_a`, `sigma_s`
    are `sigma_t (1 - albedo_k)`, `sigma_t albedo_k`).
    """
    for name, v in (("sigma_a", sigma_a), ("sigma_s", sigma_s)):
        _check(name, v, np.isfinite(v) and v >= 0, "finite and >= 0 (mm^-1)")
    _check("sigma_a + sigma_s", sigma_a + sigma_s, sigma_a + sigma_s > 0, "> 0 (mm^-1)")
    _check("g", g, np.isfinite(g) and abs(g) < 1, "in (-1, 1)")
    _check("eta", eta, np.isfinite(eta) and eta > 0, "finite and > 0")
    _check("theta_i", theta_i, np.isfinite(theta_i) and 0 <= theta_i < 90, "in [0, 90) degrees")
    _check("n_batches", n_batches, int(n_batches) >= 2, ">= 2")
    _check("n_photons", n_photons, int(n_photons) >= n_batches, f">= n_batches ({n_batches})")
    _check("max_steps", max_steps, int(max_steps) >= 1, ">= 1")
    sigma_t = float(sigma_a) + float(sigma_s)
    walk_albedo = float(sigma_s) / sigma_t
    if albedos is not None:
        alb = np.atleast_1d(np.asarray(albedos, np.float64))
        _check(
            "albedos",
            alb.tolist()[:4],
            alb.ndim == 1
            and alb.size >= 1
            and bool(np.all((alb > 0) & (alb <= walk_albedo * (1 + 1e-12)))),
            f"a 1-D list in (0, sigma_s / sigma_t = {walk_albedo:.6g}]",
        )
        log_ratios = np.minimum(np.log(alb / walk_albedo), 0.0)
    else:
        log_ratios = np.zeros(1)
    if w_min is None:
        w_min = max(0.25 * (float(sigma_s) / sigma_t) ** 2, 1e-6)
    if w_survive is None:
        w_survive = 2.0 * w_min
    _check("w_min, w_survive", (w_min, w_survive), 0 < w_min <= w_survive, "0 < w_min <= w_survive")
    sigmap_t = float(sigma_a) + float(sigma_s) * (1.0 - float(g))
    edges = default_edges(sigmap_t) if r_edges is None else np.asarray(r_edges, np.float64)
    _check(
        "r_edges",
        np.asarray(r_edges).ravel()[:4].tolist() if r_edges is not None else None,
        edges.ndim == 1 and edges.size >= 2 and edges[0] == 0 and np.all(np.diff(edges) > 0),
        "a 1-D increasing array starting at 0",
    )
    r_cap = 10.0 * float(edges[-1]) if r_cap is None else float(r_cap)
    _check("r_cap", r_cap, r_cap > 0, "> 0 (mm)")
    n_photons, n_batches = int(n_photons), int(n_batches)
    pool = max(int(pool), n_batches)
    pool = -(-pool // n_batches) * n_batches
    n_bins = edges.size - 1
    n_cols = 2 * (n_bins + 1)

    dtype = float_dtype()
    ti = math.radians(float(theta_i))
    sin_t = math.sin(ti) / float(eta)
    cos_t = math.sqrt(max(1.0 - sin_t * sin_t, 0.0))
    specular = float(fresnel_reflectance(math.cos(ti), float(eta)))
    params = tuple(
        jnp.asarray(v, dtype)
        for v in (
            sigma_t,
            float(sigma_s) / sigma_t,
            float(g),
            1.0 / float(eta),
            sin_t,
            -cos_t,
            r_cap * r_cap,
        )
    ) + (
        jnp.asarray(int(max_steps), jnp.int32),
        jnp.asarray(w_min, dtype),
        jnp.asarray(w_survive, dtype),
        jnp.asarray(log_ratios, dtype),
    )
    edges_j = jnp.asarray(edges, dtype)
    ratios = edges[2:] / edges[1:-1]
    log_bins = bool(ratios.size >= 1 and np.allclose(ratios, ratios[0], rtol=1e-9, atol=0))
    key = jax.random.key(int(seed))

    t0 = time.perf_counter()
    state = _empty_state(pool, n_batches, dtype)
    launched = jnp.asarray(0, jnp.int32)
    n_k = log_ratios.size
    total = np.zeros((n_batches * n_cols, n_k, _NQ), np.float64)
    it = 0
    report = progress if callable(progress) else None
    last_print = t0
    while True:
        state, launched, tab = _advance(
            state,
            launched,
            key,
            jnp.asarray(it, jnp.int32),
            jnp.asarray(n_photons, jnp.int32),
            params,
            edges_j,
            n_iter=n_iter,
            n_cols=n_cols,
            n_batches=n_batches,
            split=split,
            log_bins=log_bins,
        )
        it += n_iter
        total += np.asarray(tab, np.float64)
        n_launched = int(launched)
        n_active = int(jnp.sum(state[-1]))
        done = n_launched - n_active
        if report is not None:
            report(done, n_photons)
        elif progress and time.perf_counter() - last_print > 5:
            last_print = time.perf_counter()
            print(f"  {done}/{n_photons} photons", flush=True)
        if n_launched >= n_photons and n_active == 0:
            break
        # drain: once every photon is launched, trace the stragglers in a smaller pool
        size = state[0].shape[0]
        if n_launched >= n_photons and size > 256 and n_active <= size // 8:
            state = _compact(state, max(size // 8, 1))
    seconds = time.perf_counter() - t0
    total = total.reshape(n_batches, n_cols, n_k, _NQ)
    if albedos is None:
        inputs = dict(sigma_a=sigma_a, sigma_s=sigma_s, g=g, eta=eta, theta_i=theta_i)
        return _finish(total[:, :, 0], edges, n_photons, specular, seconds, inputs)
    return tuple(
        _finish(
            total[:, :, k],
            edges,
            n_photons,
            specular,
            seconds,
            dict(sigma_a=sigma_t * (1 - a), sigma_s=sigma_t * a, g=g, eta=eta, theta_i=theta_i),
        )
        for k, a in enumerate(alb)
    )


def _finish(tab, edges, n_photons, specular, seconds, inputs) -> Reference:
    n_batches, n_cols, _ = tab.shape
    n_bins = edges.size - 1
    t_in = 1.0 - specular
    nb = tab[:, :, _LAUNCH].sum(1)  # photons per batch
    if np.any(nb == 0):
        raise ValueError("reference.simulate: too few photons for the batches")

    def est(t):
        """Ratio estimate sum(t) / N per unit incident power and its standard error;
        `t` has the batch axis first."""
        t = np.asarray(t, np.float64)
        mean = t.sum(0) / n_photons
        resid = t - mean * nb.reshape((-1,) + (1,) * (t.ndim - 1))
        var = n_batches / (n_batches - 1) * np.sum(resid**2, 0) / n_photons**2
        return mean * t_in, np.sqrt(var) * t_in

    w = tab[:, :, _W]
    multi_bins, single_bins = w[:, : n_bins + 1], w[:, n_bins + 1 :]
    area = np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    prof, prof_se = est((multi_bins + single_bins)[:, :n_bins] / area)
    sprof, sprof_se = est(single_bins[:, :n_bins] / area)
    mprof, mprof_se = est(multi_bins[:, :n_bins] / area)
    diffuse = est(w.sum(1))
    single = est(single_bins.sum(1))
    multiple = est(multi_bins.sum(1))
    beyond = est(multi_bins[:, n_bins] + single_bins[:, n_bins])
    absorbed = est(tab[:, :, _ABS].sum(1))
    lost = est(tab[:, :, _LOST].sum(1))
    roulette = est(tab[:, :, _RR].sum(1))
    steps = tab[:, :, _STEPS].sum() / n_photons
    counts = tab[:, :, _N].sum(0)
    counts = counts[:n_bins] + counts[n_bins + 1 : 2 * n_bins + 1]
    r_mid = 2.0 / 3.0 * (edges[1:] ** 3 - edges[:-1] ** 3) / (edges[1:] ** 2 - edges[:-1] ** 2)
    f = float
    return Reference(
        sigma_a=f(inputs["sigma_a"]),
        sigma_s=f(inputs["sigma_s"]),
        g=f(inputs["g"]),
        eta=f(inputs["eta"]),
        theta_i=f(inputs["theta_i"]),
        n_photons=int(n_photons),
        n_batches=int(n_batches),
        r_edges=edges,
        r=r_mid,
        profile=prof,
        profile_stderr=prof_se,
        single_profile=sprof,
        single_profile_stderr=sprof_se,
        multiple_profile=mprof,
        multiple_profile_stderr=mprof_se,
        counts=counts.astype(np.int64),
        specular=f(specular),
        diffuse=f(diffuse[0]),
        diffuse_stderr=f(diffuse[1]),
        single=f(single[0]),
        single_stderr=f(single[1]),
        multiple=f(multiple[0]),
        multiple_stderr=f(multiple[1]),
        beyond=f(beyond[0]),
        beyond_stderr=f(beyond[1]),
        absorbed=f(absorbed[0]),
        absorbed_stderr=f(absorbed[1]),
        lost=f(lost[0]),
        lost_stderr=f(lost[1]),
        roulette=f(roulette[0]),
        roulette_stderr=f(roulette[1]),
        steps_per_photon=f(steps),
        seconds=f(seconds),
    )


def merge(*refs: Reference) -> Reference:
    """Pool independent runs of the same problem (different seeds) into one result.

    **Arguments:** `Reference`s with the same inputs, bins and normalisation.

    **Returns:** the photon-weighted means; standard errors combined as independent
    (`sqrt(sum (N_i se_i)^2) / N`); counts, photons, batches and seconds added.
    """
    if not refs:
        raise ValueError("merge: nothing to merge")
    a = refs[0]
    keys = ("sigma_a", "sigma_s", "g", "eta", "theta_i", "normalization", "specular")
    for b in refs[1:]:
        if any(getattr(a, k) != getattr(b, k) for k in keys) or not np.array_equal(
            a.r_edges, b.r_edges
        ):
            raise ValueError("merge: the runs differ in their inputs, bins or normalisation")
    n = np.array([r.n_photons for r in refs], np.float64)
    total = n.sum()
    out = {}
    for name in _TALLIES:
        if name.endswith("_stderr"):
            continue
        vals = [getattr(r, name) for r in refs]
        ses = [getattr(r, name + "_stderr") for r in refs]
        out[name] = sum(ni * v for ni, v in zip(n, vals, strict=True)) / total
        out[name + "_stderr"] = (
            np.sqrt(sum((ni * e) ** 2 for ni, e in zip(n, ses, strict=True))) / total
        )
        if np.ndim(out[name]) == 0:
            out[name], out[name + "_stderr"] = float(out[name]), float(out[name + "_stderr"])
    return dataclasses.replace(
        a,
        n_photons=int(total),
        n_batches=sum(r.n_batches for r in refs),
        counts=sum(r.counts for r in refs),
        steps_per_photon=float(
            sum(ni * r.steps_per_photon for ni, r in zip(n, refs, strict=True)) / total
        ),
        seconds=float(sum(r.seconds for r in refs)),
        **out,
    )


# --- colour --------------------------------------------------------------------------------
def simulate_medium(
    medium: Medium,
    *,
    r_edges: ArrayLike | None = None,
    seed: int = 0,
    n_per_decade: int = 10,
    **kwargs,
) -> tuple[Reference, Reference, Reference]:
    """`simulate` for each RGB channel of a `Medium` (channel `c` uses seed `seed + c`).

    **Arguments:** `medium`; `r_edges` (mm) shared by the channels (default: `[0]`, then
    `n_per_decade` logarithmic bins per decade from 0.01 reduced mean free paths of the
    densest channel to 100 of the thinnest); the other keywords as in `simulate`.

    **Returns:** three `Reference`s (R, G, B), per unit incident power.
    """
    sa = np.asarray(medium.sigma_a, np.float64)
    ss = np.asarray(medium.sigma_s, np.float64)
    g = np.broadcast_to(np.asarray(medium.g, np.float64), (3,))
    eta = float(medium.eta)
    if r_edges is None:
        spt = sa + ss * (1.0 - g)
        lo, hi = 1e-2 / spt.max(), 1e2 / spt.min()
        n = int(np.ceil(n_per_decade * np.log10(hi / lo)))
        r_edges = np.concatenate([[0.0], np.geomspace(lo, hi, n + 1)])
    out = tuple(
        simulate(sa[c], ss[c], g[c], eta, r_edges=r_edges, seed=seed + c, **kwargs)
        for c in range(3)
    )
    return out  # type: ignore[return-value]


def to_profile(
    refs: tuple[Reference, ...],
    *,
    component: str = "multiple",
    normalization: str = "entered",
):
    """The channels of `simulate_medium` as a `sssjax.measure.Profile` (for `fit_profile`).

    **Arguments:** `refs`, one `Reference` per channel on the same bins; `component`
    `"multiple"` (what the diffusion profiles model), `"total"` or `"single"`;
    `normalization` `"entered"` (like `dipole.Rd`) or `"incident"`.

    **Returns:** a `Profile` with `r` the bins' area-weighted radii, `mean` and `stderr`
    `(n, len(refs))` in mm^-2, `counts` the fewest exit events of a channel per bin, and
    `bounds` the bins' edges (so `fit_profile` averages its model over each bin).
    """
    from .measure import Profile

    attr = {"multiple": "multiple_profile", "total": "profile", "single": "single_profile"}
    if component not in attr:
        raise ValueError(f"to_profile: component must be one of {sorted(attr)}, got {component!r}")
    if normalization not in ("entered", "incident"):
        raise ValueError(
            f"to_profile: normalization must be 'entered' or 'incident', got {normalization!r}"
        )
    if any(not np.array_equal(r.r_edges, refs[0].r_edges) for r in refs):
        raise ValueError("to_profile: the channels have different r_edges")
    refs = [r.entered() if normalization == "entered" else r for r in refs]
    a = attr[component]
    mean = np.stack([getattr(r, a) for r in refs], 1)
    se = np.stack([getattr(r, a + "_stderr") for r in refs], 1)
    counts = np.min(np.stack([r.counts for r in refs], 1), 1)
    e = np.asarray(refs[0].r_edges, np.float64)
    bounds = np.stack([e[:-1], e[1:]], 1)
    return Profile(r=refs[0].r.copy(), mean=mean, stderr=se, counts=counts, bounds=bounds)


# --- closed forms for single scattering ----------------------------------------------------
def _mu_nodes(eta: float, n: int):
    """Gauss-Legendre nodes and weights for the exit cosine `mu` over the escape cone."""
    mu_c = math.sqrt(1.0 - 1.0 / eta**2) if eta > 1 else 0.0
    x, wx = np.polynomial.legendre.leggauss(n)
    mu = mu_c + (1.0 - mu_c) * (x + 1.0) / 2.0
    return mu, wx * (1.0 - mu_c) / 2.0


# NumPy float64 re-statements of the HG phase and the Fresnel reflectance (the walk uses
# `sssjax.dipole`'s): kept separate on purpose, so the closed forms that test the walk do not
# share its code.
def _hg(cos, g):
    return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * cos) ** 1.5)


def _fresnel_np(cos_i, eta):
    cos_i = np.clip(np.abs(cos_i), 0.0, 1.0)
    sin2_t = (1.0 - cos_i**2) / eta**2
    cos_t = np.sqrt(np.clip(1.0 - sin2_t, 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
        rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return np.where(sin2_t >= 1.0, 1.0, 0.5 * (rs**2 + rp**2))


def single_scatter_total(
    sigma_a: float,
    sigma_s: float,
    g: float = 0.0,
    eta: float = 1.3,
    theta_i: float = 0.0,
    n: int = 400,
) -> float:
    """Exact total single-scattering reflectance of the semi-infinite medium (quadrature).

    A photon entering along a refracted direction with `|cos| = mu_0` collides at depth
    `z` with density `(sigma_t / mu_0) e^{-sigma_t z / mu_0}`, scatters into `w` (cosine `mu`
    with the normal) with probability `albedo p(w_0 . w)` and reaches the surface unscattered
    with `e^{-sigma_t z / mu}`; integrating over `z` leaves
    `(1 - F_in) albedo int_{mu > 0} p(w_0 . w) (1 - F(mu, 1/eta)) mu / (mu + mu_0) dw`,
    evaluated with Gauss-Legendre in `mu` (over the escape cone) and the trapezoidal rule in
    azimuth.

    **Arguments:** as in `simulate`; `n` quadrature nodes in `mu`.

    **Returns:** the fraction of the incident power (dimensionless).
    """
    ti = math.radians(theta_i)
    sin0 = math.sin(ti) / eta
    mu0 = math.sqrt(1.0 - sin0 * sin0)
    mu, wmu = _mu_nodes(eta, n)
    phi = np.linspace(0.0, 2 * np.pi, 2 * n, endpoint=False)
    M, P = np.meshgrid(mu, phi, indexing="ij")
    cos = sin0 * np.sqrt(1.0 - M**2) * np.cos(P) - mu0 * M
    f = _hg(cos, g) * (1.0 - _fresnel_np(M, 1.0 / eta)) * M / (M + mu0)
    integral = np.sum(wmu[:, None] * f) * (2 * np.pi / phi.size)
    t_in = 1.0 - float(_fresnel_np(np.cos(ti), eta))
    return float(t_in * sigma_s / (sigma_a + sigma_s) * integral)


def _single_nodes(g: float, eta: float, n_panels: int):
    """Quadrature in the exit polar angle `theta` (`mu = cos theta`) for single scattering:
    panels geometric towards `theta = 0`, where the factor `e^{-k a / sin theta}` of a small
    radius `a` varies on the scale `theta ~ a sigma_t`, and towards the critical angle, where
    the Fresnel transmittance has a square-root kink (and far from the beam all the light
    leaves). Returns `mu`, `sin theta`, the weights in `mu` and the angular factor."""
    theta_c = math.asin(1.0 / eta) if eta > 1 else math.pi / 2
    half = np.geomspace(1e-9, theta_c / 2, n_panels // 2)
    panels = np.unique(np.concatenate([[0.0], half, theta_c - half[::-1], [theta_c]]))
    x, wx = np.polynomial.legendre.leggauss(24)
    lo, hi = panels[:-1, None], panels[1:, None]
    theta = (lo + (hi - lo) * (x + 1) / 2).ravel()
    wmu = ((hi - lo) / 2 * wx).ravel() * np.sin(theta)  # d mu = sin theta d theta
    mu, s = np.cos(theta), np.sin(theta)
    base = mu * _hg(-mu, g) * (1.0 - _fresnel_np(mu, 1.0 / eta)) / (1.0 + mu)
    return mu, s, wmu, base


def single_scatter_exitance(
    r: ArrayLike,
    sigma_a: float,
    sigma_s: float,
    g: float = 0.0,
    eta: float = 1.3,
    n_panels: int = 48,
) -> np.ndarray:
    """Exact single-scattering exitance at distances `r` > 0 (mm), normal incidence: the
    point value (the derivative in `r` of `single_scatter_profile`'s annulus integral,
    `albedo int base(mu) (k / s) e^{-k r / s} dmu / r`), without the cancellation of a
    narrow annulus far from the beam.

    **Returns:** `r`'s shape, mm^-2 per unit incident power.
    """
    r = np.asarray(r, np.float64)
    sigma_t = sigma_a + sigma_s
    mu, s, wmu, base = _single_nodes(g, eta, n_panels)
    k = sigma_t * (1.0 + mu)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        ex = np.exp(-k * r[..., None] / s) * (k / s)
    ex = np.nan_to_num(ex, nan=0.0, posinf=0.0)
    t_in = 1.0 - float(_fresnel_np(1.0, eta))
    return t_in * sigma_s / sigma_t * np.sum(wmu * base * ex, axis=-1) / r


def single_scatter_profile(
    r_edges: ArrayLike,
    sigma_a: float,
    sigma_s: float,
    g: float = 0.0,
    eta: float = 1.3,
    n_panels: int = 48,
) -> np.ndarray:
    """Exact single-scattering exitance per radial bin, normal incidence (quadrature).

    In polar coordinates `(L, theta)` around the entry point (`mu = cos theta`), a collision
    at depth `z = L mu` that sends light to the surface point at `r = L sin theta` gives the
    exitance `sigma_s e^{-sigma_t z} p(-mu) e^{-sigma_t L} (1 - F) mu / L^2`; the integral over
    an annulus `[a, b]` in `L` is closed-form, leaving
    `2 pi albedo int mu p(-mu) (1 - F(mu)) / (1 + mu) [e^{-k a / s} - e^{-k b / s}] dmu`
    with `k = sigma_t (1 + mu)`, `s = sqrt(1 - mu^2)`, divided by the annulus area.

    **Arguments:** `r_edges` (mm); the coefficients as in `simulate`; `n_panels` quadrature
    panels in `theta` (24 Gauss-Legendre nodes each).

    **Returns:** `(len(r_edges) - 1,)` mean exitance per bin, mm^-2 per unit incident power.
    """
    edges = np.asarray(r_edges, np.float64)
    sigma_t = sigma_a + sigma_s
    mu, s, wmu, base = _single_nodes(g, eta, n_panels)
    k = sigma_t * (1.0 + mu)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        ex = np.exp(-k[None, :] * edges[:, None] / s[None, :])  # (edges, nodes)
    ex = np.where(np.isfinite(edges)[:, None], np.nan_to_num(ex, nan=0.0), 0.0)
    power = 2 * np.pi * sigma_s / sigma_t * np.sum(wmu * base * (ex[:-1] - ex[1:]), axis=1)
    area = np.pi * (edges[1:] ** 2 - edges[:-1] ** 2)
    t_in = 1.0 - float(_fresnel_np(1.0, eta))
    return t_in * power / area
